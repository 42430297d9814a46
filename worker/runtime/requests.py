"""Render and export requests: parse the gateway's request, run it on an engine, post the reply."""

from __future__ import annotations

import json
import logging
from typing import Any

import cv2
import numpy as np
import redis

from protocol import keys
from protocol.codec import pack
from worker.runtime.engine import SessionEngine

log = logging.getLogger(__name__)
REPLY_TTL_S = 60


class RequestError(ValueError):
    """A request the engine cannot serve; `status` is the HTTP status the gateway returns."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status


def serve_request(engine: SessionEngine, kind: str, params: dict[str, Any]) -> tuple[str, bytes]:
    """(content type, body) for a "render" or "export_ply" request (params "format": ply, spz or splat)."""
    if kind == "export_ply":  # the map in any of worker.mapping.map_formats.FORMATS (the name predates them)
        from protocol.splats import FORMATS, encode_map

        fmt = str(params.get("format", "ply"))
        if fmt not in FORMATS:
            raise RequestError(400, f"unknown map format {fmt!r}; choose one of {', '.join(FORMATS)}")
        try:
            encoded = encode_map(engine.export_ply(), fmt, int(params.get("sh_degree", 0)))
        except ValueError as err:  # e.g. a map without Gaussians (the passthrough engine's point list)
            raise RequestError(409, f"the map cannot be written as {fmt}: {err}") from err
        return encoded.content_type, encoded.body
    if kind != "render":
        raise RequestError(400, f"unknown request kind {kind!r}")
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
