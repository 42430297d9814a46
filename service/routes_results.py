"""What a session produced: trajectory (JSON or TUM), rendered views and the map (PLY)."""

from __future__ import annotations

import asyncio
import json
import re
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import PlainTextResponse

from protocol.lens import is_identity
from protocol.limits import MAX_RENDER_SIDE, MIN_RENDER_SIDE
from protocol.poses import split_similarity
from service.auth import Principal, caller
from service.deps import registry, session_for
from service.pose_check import pose_problem
from service.registry import ArchiveUnavailable, Registry, engine_camera, parse_session
from service.schemas import ErrorBody, Trajectory
from service.worker_requests import WORKER_ANSWERS, ask_worker

router = APIRouter(prefix="/v1/sessions/{session_id}", tags=["results"],
                   responses={401: {"model": ErrorBody}, 403: {"model": ErrorBody}, 404: {"model": ErrorBody}})

# A number as JSON Schema (ECMA 262) and Python's `re` both read it; render_params applies the same pattern
_NUMBER = r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?"
RENDER_POSE_PATTERN = rf"^ *{_NUMBER} *(?:, *{_NUMBER} *){{15}}$"


@router.get("/trajectory", response_model=Trajectory,
            responses={200: {"content": {"application/json": {}, "text/plain": {"description": "TUM format"}}},
                       503: {"model": ErrorBody, "description": "the session was moved to the blob store and this "
                             "gateway has none configured (FLASHMONO_BLOB_DIR)"}})
async def get_trajectory(
    session_id: str,
    request: Request,
    format: Annotated[Literal["json", "tum"], Query(description="json, or TUM text")] = "json",
    which: Annotated[Literal["all", "keyframes"], Query()] = "all",
    principal: Principal = Depends(caller),
    reg: Registry = Depends(registry),
):
    """The current trajectory (camera-to-world poses by frame seq) at the session's current revision."""
    request.app.state.auth.require(principal, "read", "stream")
    record = await session_for(reg, principal, session_id, write=False)
    try:
        poses = await reg.trajectory(session_id, which, archived=record.get("archived") == "1")
    except ArchiveUnavailable as err:
        raise HTTPException(503, str(err)) from err
    if format == "tum":
        # off the event loop: converting a long trajectory would stall every stream of this gateway
        return PlainTextResponse(await asyncio.to_thread(tum_text, poses), media_type="text/plain")
    return {"session_id": session_id, "revision": int(record.get("revision") or 0), "which": which, "poses": poses,
            "intrinsics": parse_session(record)["estimated_intrinsics"]}


def tum_text(poses: list[dict]) -> str:
    """TUM lines "timestamp tx ty tz qx qy qz qw" (the rotation of a Sim(3) pose without its scale)."""
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    if poses:
        _, quats, trans = split_similarity(np.asarray([p["pose"] for p in poses], dtype=np.float64))
        for p, q, t in zip(poses, quats.tolist(), trans.tolist()):
            w, x, y, z = q
            lines.append(f"{p['timestamp']:.6f} {t[0]:.8f} {t[1]:.8f} {t[2]:.8f} {x:.8f} {y:.8f} {z:.8f} {w:.8f}")
    return "\n".join(lines) + "\n"


@router.get("/render", response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "color: RGB PNG; depth: 16-bit PNG, mm"},
                       400: {"model": ErrorBody, "description": "the pose is not a camera-to-world pose (not rigid, "
                             "a reflection, ...), the size exceeds the pixel limit, or the camera is not given and "
                             "the session has no intrinsics"}, **WORKER_ANSWERS})
async def render_view(
    session_id: str,
    request: Request,
    pose: Annotated[str, Query(description="camera-to-world 4x4 as 16 comma-separated numbers, row-major: a rigid "
                               "transform or a similarity [sR|t; 0 0 0 1] (a 400 otherwise)",
                               json_schema_extra={"pattern": RENDER_POSE_PATTERN})],
    width: Annotated[int | None, Query(ge=MIN_RENDER_SIDE, le=MAX_RENDER_SIDE)] = None,
    height: Annotated[int | None, Query(ge=MIN_RENDER_SIDE, le=MAX_RENDER_SIDE)] = None,
    fx: Annotated[float | None, Query(gt=0)] = None,
    fy: Annotated[float | None, Query(gt=0)] = None,
    cx: Annotated[float | None, Query()] = None,
    cy: Annotated[float | None, Query()] = None,
    kind: Annotated[Literal["color", "depth"], Query()] = "color",
    exposure_of: Annotated[int | None, Query(ge=0, description="a frame's seq: the colours under the exposure the "
                                             "camera had at that frame (interpolated between the keyframes around "
                                             "it), as its photo shows them; default: the map's exposure-normalised "
                                             "colours")] = None,
    principal: Principal = Depends(caller),
    reg: Registry = Depends(registry),
) -> Response:
    """Render the session's map from any camera. Defaults: the session's intrinsics (scaled to width x height).
    Colour shows the surfels over the map's background (what keyframes saw in each direction where the map has no
    surface, such as the sky); depth is the surfels' own (0 where there are none). While the session is
    `finishing`, the map as refined so far (as /map)."""
    request.app.state.auth.require(principal, "read", "stream")
    record = await session_for(reg, principal, session_id, write=False)
    params = render_params(record, pose, width, height, fx, fy, cx, cy, kind,
                           request.app.state.settings.max_render_pixels)
    if exposure_of is not None:
        params["exposure_of"] = exposure_of
    return await _ask_worker(request, reg, session_id, record, "render", params)


@router.get("/map.ply", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}, "description": "binary PLY"},
                       **WORKER_ANSWERS})
async def export_map(
    session_id: str,
    request: Request,
    sh_degree: Annotated[int, Query(ge=0, le=3, description="spherical-harmonics degree of the colour properties: 0 "
                                    "(default) writes f_dc only, 68 bytes a surfel; 3 adds the 45 f_rest "
                                    "coefficients (all zero: the map's colour is view-independent) that fixed-record "
                                    "3DGS readers such as SIBR expect, 248 bytes a surfel")] = 0,
    principal: Principal = Depends(caller),
    reg: Registry = Depends(registry),
) -> Response:
    """The session's 2DGS surfel map as binary PLY (3DGS property layout: x y z nx ny nz f_dc_0..2 [f_rest_..]
    opacity scale_0..2 rot_0..3)."""
    request.app.state.auth.require(principal, "read", "stream")
    record = await session_for(reg, principal, session_id, write=False)
    response = await _ask_worker(request, reg, session_id, record, "export_ply", {"sh_degree": sh_degree})
    response.headers["content-disposition"] = f'attachment; filename="{session_id}.ply"'
    return response


@router.get("/map", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}},
                             "description": "the map file (X-Map-Format, X-Map-Revision headers)"},
                       **WORKER_ANSWERS})
async def export_map_as(
    session_id: str,
    request: Request,
    format: Annotated[Literal["ply", "spz", "splat"], Query(
        description="ply: binary 3DGS-layout PLY, 68 bytes a surfel (248 with sh_degree=3); spz: Niantic SPZ "
                    "version 3 (gzip, quantised, right-up-back axes as its specification says), about 10 bytes a "
                    "surfel; splat: antimatter15's 32-byte records, world axes as in the PLY. 2D surfels carry a "
                    "zero (splat) or tiny (ply, spz) third scale: flat Gaussians, orientation kept")] = "ply",
    sh_degree: Annotated[int, Query(ge=0, le=3, description="PLY only: 0 or 3 (see /map.ply)")] = 0,
    principal: Principal = Depends(caller),
    reg: Registry = Depends(registry),
) -> Response:
    """The session's surfel map in the format a web viewer reads (PLY, SPZ or .splat). While the session is
    `finishing`, the map as refined so far, answered at once (the final refinement lets the request in between two
    of its steps); fetch it again once the session is `finished` for the final one."""
    request.app.state.auth.require(principal, "read", "stream")
    record = await session_for(reg, principal, session_id, write=False)
    response = await _ask_worker(request, reg, session_id, record, "export_ply",
                                 {"sh_degree": sh_degree, "format": format})
    response.headers["content-disposition"] = f'attachment; filename="{session_id}.{format}"'
    response.headers["x-map-format"] = format
    response.headers["x-map-revision"] = str(record.get("revision") or 0)
    return response


async def _ask_worker(request: Request, reg: Registry, session_id: str, record: dict[str, str], kind: str,
                      params: dict) -> Response:
    content_type, body = await ask_worker(request, reg, session_id, record, kind, params)
    return Response(content=body, media_type=content_type)


def render_params(record: dict[str, str], pose: str, width: int | None, height: int | None, fx: float | None,
                  fy: float | None, cx: float | None, cy: float | None, kind: str, max_pixels: int) -> dict:
    """Validated render parameters, defaults filled from the session's intrinsics; 400 on bad input."""
    if re.search(RENDER_POSE_PATTERN, pose) is None:  # search: JSON Schema's reading of a pattern
        raise HTTPException(400, "pose must be 16 comma-separated numbers (camera-to-world 4x4, row-major)")
    values = [float(v) for v in pose.split(",")]
    problem = pose_problem(values)
    if problem:
        raise HTTPException(400, f"pose must be a camera-to-world [sR|t; 0 0 0 1] matrix: {problem}")
    session_k = json.loads(record.get("intrinsics") or "null")
    if session_k is not None and not is_identity(session_k.get("distortion")):
        session_k = engine_camera(record)  # a distorted camera renders as the pinhole its frames were brought to
    if width is None or height is None:
        if session_k is None:
            raise HTTPException(400, "width and height are required (the session has no intrinsics yet)")
        width, height = width or session_k["width"], height or session_k["height"]
    if width * height > max_pixels:
        raise HTTPException(400, f"{width}x{height} exceeds the limit of {max_pixels} pixels")
    if None in (fx, fy, cx, cy):
        if session_k is None:
            raise HTTPException(400, "fx, fy, cx, cy are required (the session has no intrinsics yet)")
        sx, sy = width / session_k["width"], height / session_k["height"]
        fx = fx if fx is not None else session_k["fx"] * sx
        fy = fy if fy is not None else session_k["fy"] * sy
        cx = cx if cx is not None else session_k["cx"] * sx
        cy = cy if cy is not None else session_k["cy"] * sy
    return {"pose": values, "width": width, "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy, "kind": kind}
