"""Render, export and map package requests: parse the gateway's request, run it on an engine, post the reply."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import redis

from protocol import keys
from protocol.codec import pack
from protocol.map_package import CONTENT_TYPE as MAP_CONTENT_TYPE
from worker.runtime.engine import SessionEngine

log = logging.getLogger(__name__)
REPLY_TTL_S = 60


class RequestError(ValueError):
    """A request the engine cannot serve; `status` is the HTTP status the gateway returns."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status


def serve_request(engine: SessionEngine, kind: str, params: dict[str, Any]) -> tuple[str, bytes]:
    """(content type, body) for a "render", "export_ply" (params "format": ply, spz or splat) or "map_package"
    (params "name", "session_ids") request."""
    serve = _SERVERS.get(kind)
    if serve is None:
        raise RequestError(400, f"unknown request kind {kind!r}")
    return serve(engine, params)


def _export_map(engine: SessionEngine, params: dict[str, Any]) -> tuple[str, bytes]:
    """The map in any of protocol.splats.FORMATS (the request's name, export_ply, predates them)."""
    from protocol.splats import FORMATS, encode_map

    fmt = str(params.get("format", "ply"))
    if fmt not in FORMATS:
        raise RequestError(400, f"unknown map format {fmt!r}; choose one of {', '.join(FORMATS)}")
    try:
        encoded = encode_map(engine.export_ply(), fmt, int(params.get("sh_degree", 0)))
    except ValueError as err:  # e.g. a map without Gaussians (the passthrough engine's point list)
        raise RequestError(409, f"the map cannot be written as {fmt}: {err}") from err
    return encoded.content_type, encoded.body


def _map_package(engine: SessionEngine, params: dict[str, Any]) -> tuple[str, bytes]:
    """The session's map as a map package (worker.maps.build_package)."""
    if getattr(engine, "mapping_stage", None) is None:
        raise RequestError(409, "this session's engine keeps no map to package (the passthrough engine, or a "
                                "session with mapping disabled)")
    from worker.maps import build_package

    name, session_ids = str(params.get("name") or ""), [str(s) for s in params.get("session_ids") or []]
    try:
        return MAP_CONTENT_TYPE, build_package(engine, name, session_ids)
    except ValueError as err:  # e.g. a map without keyframes (MapPackageError is one)
        raise RequestError(409, f"the session's map cannot be packaged: {err}") from err


def _render(engine: SessionEngine, params: dict[str, Any]) -> tuple[str, bytes]:
    """A PNG of the map from a camera: colour (RGB) or depth (16-bit, millimetres)."""
    pose = np.asarray(params["pose"], dtype=np.float64).reshape(4, 4)
    width, height = int(params["width"]), int(params["height"])
    K = np.array([[params["fx"], 0.0, params["cx"]], [0.0, params["fy"], params["cy"]], [0.0, 0.0, 1.0]])
    exposure_of = params.get("exposure_of")
    rgb, depth = engine.render_view(pose, K, width, height,
                                    as_captured_at=None if exposure_of is None else int(exposure_of))
    if params.get("kind", "color") == "depth":
        mm = np.clip(np.nan_to_num(np.asarray(depth, dtype=np.float64)) * 1000.0, 0, 65535).round().astype(np.uint16)
        ok, buf = cv2.imencode(".png", mm)
    else:
        ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RequestError(500, "PNG encoding failed")
    return "image/png", buf.tobytes()


_SERVERS: dict[str, Callable[[SessionEngine, dict[str, Any]], tuple[str, bytes]]] = {
    "render": _render, "export_ply": _export_map, "map_package": _map_package}


def handle_request(client: redis.Redis, engine: SessionEngine | None, fields: dict[bytes, bytes]) -> None:
    """Run one request entry {id, kind, params} and post its reply (errors included) to `keys.reply(id)`."""
    request_id = fields.get(b"id", b"").decode()
    if not request_id:
        log.warning("request without id dropped")
        return
    try:
        if engine is None:
            raise RequestError(404, "the session has no map yet")
        params = json.loads(fields.get(b"params", b"{}"))
        content_type, body = serve_request(engine, fields.get(b"kind", b"").decode(), params)
        reply = {"ok": True, "content_type": content_type, "body": body}
    except RequestError as err:
        reply = {"ok": False, "status": err.status, "detail": str(err)}
    except (ValueError, KeyError, TypeError) as err:
        reply = {"ok": False, "status": 400, "detail": f"bad request: {err}"}
    except Exception as err:  # the engine failed: report it, keep the worker alive
        log.exception("request %s failed", request_id)
        reply = {"ok": False, "status": 500, "detail": f"engine error: {err}"}
    pipe = client.pipeline(transaction=False)
    pipe.rpush(keys.reply(request_id), pack(reply))
    pipe.expire(keys.reply(request_id), REPLY_TTL_S)
    pipe.execute()
