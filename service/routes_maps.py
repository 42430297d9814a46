"""Maps as a resource: /v1/maps. A finished session's map saved (or an exported package uploaded), listed, read,
exported, served as splats and deleted; sessions start in one with `map_id` (routes_sessions)."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from protocol.map_package import CONTENT_TYPE, FILE_SUFFIX, MapPackage, MapPackageError, decode_package
from protocol.map_store import MapNotFound
from protocol.splats import MapFormat, encode_map, ply_without
from service.auth import Principal, caller
from service.deps import map_for, map_store, registry, session_for
from service.maps import MapStore, parse_map, versions
from service.registry import Registry
from service.schemas import ErrorBody, Map, MapCreate, MapList, MapSessionList
from service.worker_requests import WORKER_ANSWERS, ask_worker

router = APIRouter(prefix="/v1/maps", tags=["maps"],
                   responses={401: {"model": ErrorBody}, 403: {"model": ErrorBody}})
PACKAGE_TYPES = (CONTENT_TYPE, "application/octet-stream")
_NOT_FOUND = {404: {"model": ErrorBody, "description": "no such map (or version)"}}
_CREATE_BODY = {"required": True, "content": {
    "application/json": {"schema": MapCreate.model_json_schema()},
    **{kind: {"schema": {"type": "string", "format": "binary", "description": "a map package (`flashmono.map/1`, as "
                                                                              "GET /v1/maps/{map_id}/export gives)"}}
       for kind in PACKAGE_TYPES}}}


@router.post("", status_code=201, response_model=Map, openapi_extra={"requestBody": _CREATE_BODY},
             responses={400: {"model": ErrorBody, "description": "the uploaded package is corrupt (what is wrong), or "
                              "the JSON body is not UTF-8 text"},
                        404: {"model": ErrorBody, "description": "no such session"},
                        409: {"model": ErrorBody, "description": "the session is not finished, failed, or its "
                              "engine keeps no map"},
                        413: {"model": ErrorBody, "description": "the body exceeds FLASHMONO_MAX_MAP_BYTES"},
                        415: {"model": ErrorBody, "description": "neither JSON nor a map package"},
                        422: {"description": "invalid JSON body"},
                        502: {"model": ErrorBody, "description": "the worker's package failed its check"},
                        **{k: v for k, v in WORKER_ANSWERS.items() if k != 409}})
async def create_map(
    request: Request,
    name: Annotated[str | None, Query(max_length=200, description="upload: the map's name (default: the "
                                                                  "package's)")] = None,
    principal: Principal = Depends(caller),
    maps: MapStore = Depends(map_store),
    reg: Registry = Depends(registry),
) -> dict[str, Any]:
    """Save a map. JSON `{"session_id", "name"}`: the map of a finished session this key created (its worker
    packages it); a map package body (`application/x-flashmono-map` or `application/octet-stream`): an exported
    map, uploaded. Needs the `stream` scope; the map belongs to the calling key."""
    request.app.state.auth.require(principal, "stream")
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind in PACKAGE_TYPES:
        data, built_by = await request.body(), []
        package = await _checked(data, request.app.state.settings.max_map_bytes, status=400)
        name = package.name if name is None else name
    elif kind == "application/json":
        body = await _map_create(request)
        record = await session_for(reg, principal, body.session_id, write=True)
        if record["status"] != "finished":
            raise HTTPException(409, f"session {body.session_id} is {record['status']}: a map is saved from a "
                                     "finished session (finish it first)")
        _, data = await ask_worker(request, reg, body.session_id, record, "map_package",
                                   {"name": body.name, "session_ids": [body.session_id]})
        package = await _checked(data, request.app.state.settings.max_map_bytes, status=502)
        name, built_by = body.name, [body.session_id]
    else:
        raise HTTPException(415, f"send JSON {{session_id, name}} or a map package ({', '.join(PACKAGE_TYPES)}), "
                                 f"not {kind or 'no content type'}")
    record = await maps.create(data, package.meta(), name, principal.key_id, built_by)
    return {**parse_map(record), "versions": versions(record), "sessions": await maps.sessions(record["id"])}


async def _map_create(request: Request) -> MapCreate:
    """The JSON body, parsed as FastAPI parses the bodies it reads itself (400: not UTF-8; 422: not JSON, or
    invalid)."""
    body = await request.body()
    if len(body) > request.app.state.settings.max_body_bytes:
        raise HTTPException(413, f"a JSON body exceeds the limit of {request.app.state.settings.max_body_bytes} "
                                 "bytes")
    try:
        return MapCreate.model_validate(json.loads(body))
    except UnicodeDecodeError as err:
        raise HTTPException(400, "the body could not be parsed (not UTF-8 text)") from err
    except json.JSONDecodeError as err:
        raise RequestValidationError([{"type": "json_invalid", "loc": ("body", err.pos), "msg": "JSON decode error",
                                       "input": {}, "ctx": {"error": err.msg}}]) from err
    except ValidationError as err:  # the same 422 body as every other invalid field
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in err.errors(include_url=False)]
                                     ) from err


async def _checked(data: bytes, max_bytes: int, status: int) -> MapPackage:
    """The package in `data`, decoded and checked off the event loop; `status` with what is wrong when corrupt
    (400: an upload; 502: a worker's)."""
    try:
        return await asyncio.to_thread(decode_package, data, max_bytes)
    except MapPackageError as err:
        raise HTTPException(413 if "over the limit" in str(err) else status, f"corrupt map package: {err}") from err


@router.get("", response_model=MapList)
async def list_maps(
    request: Request,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    cursor: Annotated[str | None, Query(max_length=200, description="next_cursor of the previous page")] = None,
    principal: Principal = Depends(caller),
    maps: MapStore = Depends(map_store),
) -> dict[str, Any]:
    """Maps, newest first. Keys with only the `stream` scope see the maps they saved."""
    request.app.state.auth.require(principal, "read", "stream")
    records, next_cursor = await maps.list(None if principal.can_read_any() else principal.key_id, limit, cursor)
    return {"maps": [parse_map(record) for record in records], "next_cursor": next_cursor}


@router.get("/{map_id}", response_model=Map, responses=_NOT_FOUND)
async def get_map(map_id: str, request: Request, principal: Principal = Depends(caller),
                  maps: MapStore = Depends(map_store)) -> dict[str, Any]:
    """A map: the latest version's metadata and size, every version, and the sessions that built or used it."""
    request.app.state.auth.require(principal, "read", "stream")
    record = await map_for(maps, principal, map_id, write=False)
    return {**parse_map(record), "versions": versions(record), "sessions": await maps.sessions(map_id)}


@router.delete("/{map_id}", status_code=204, responses=_NOT_FOUND)
async def delete_map(map_id: str, request: Request, principal: Principal = Depends(caller),
                     maps: MapStore = Depends(map_store)) -> Response:
    """Delete the map, every version of it; sessions already running in it keep the copy they loaded."""
    request.app.state.auth.require(principal, "stream")
    await maps.delete(map_id, await map_for(maps, principal, map_id, write=True))
    return Response(status_code=204)


_VERSION = Query(ge=1, description="a version (GET /v1/maps/{map_id} lists them; default: the latest)")


@router.get("/{map_id}/export", response_class=Response, responses={
    200: {"content": {CONTENT_TYPE: {}}, "description": "the map package (`flashmono.map/1`), to upload elsewhere"},
    **_NOT_FOUND})
async def export_map(map_id: str, request: Request, version: Annotated[int | None, _VERSION] = None,
                     principal: Principal = Depends(caller), maps: MapStore = Depends(map_store)) -> Response:
    """The map's package as stored: keyframes (poses, intrinsics, JPEG images, depth) and surfels."""
    data, version = await _package(request, principal, maps, map_id, version)
    return Response(content=data, media_type=CONTENT_TYPE, headers={
        "content-disposition": f'attachment; filename="{map_id}.v{version}{FILE_SUFFIX}"'})


@router.get("/{map_id}/map", response_class=Response, responses={
    200: {"content": {"application/octet-stream": {}}, "description": "the map file (X-Map-Format header)"},
    **_NOT_FOUND})
async def map_file(
    map_id: str,
    request: Request,
    format: Annotated[MapFormat, Query(description="as GET /v1/sessions/{session_id}/map")] = "ply",
    sh_degree: Annotated[int, Query(ge=0, le=3, description="PLY only: 0 or 3 (see /v1/sessions/{session_id}/map.ply)")
                         ] = 0,
    version: Annotated[int | None, _VERSION] = None,
    principal: Principal = Depends(caller),
    maps: MapStore = Depends(map_store),
) -> Response:
    """The map's surfels in the format a web viewer reads (PLY, SPZ or .splat), as sessions serve theirs."""
    data, version = await _package(request, principal, maps, map_id, version)
    encoded = await asyncio.to_thread(_encoded_surfels, data, format, sh_degree)
    return Response(content=encoded.body, media_type=encoded.content_type, headers={
        "content-disposition": f'attachment; filename="{map_id}.v{version}.{encoded.extension}"',
        "x-map-format": format})


def _encoded_surfels(data: bytes, fmt: str, sh_degree: int) -> Any:
    ply = decode_package(data).surfels_ply
    return encode_map(ply_without(ply, "keyframe_id"), fmt, sh_degree)


async def _package(request: Request, principal: Principal, maps: MapStore, map_id: str,
                   version: int | None) -> tuple[bytes, int]:
    request.app.state.auth.require(principal, "read", "stream")
    record = await map_for(maps, principal, map_id, write=False)
    version = int(record["latest"]) if version is None else version
    try:
        return await maps.package(map_id, version), version
    except MapNotFound as err:
        raise HTTPException(404, str(err)) from err


@router.get("/{map_id}/sessions", response_model=MapSessionList, responses=_NOT_FOUND)
async def map_sessions(map_id: str, request: Request, principal: Principal = Depends(caller),
                       maps: MapStore = Depends(map_store)) -> dict[str, Any]:
    """The sessions that built the map (its map saved as this one) or were created in it, with their status."""
    request.app.state.auth.require(principal, "read", "stream")
    await map_for(maps, principal, map_id, write=False)
    return {"map_id": map_id, "sessions": await maps.sessions(map_id)}
