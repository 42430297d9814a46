"""The gateway's REST calls, described once and executed by both the sync and the async client.

Each function returns a `Call`: method, path, query, JSON body and a `parse(response)` that turns a successful
`httpx.Response` into the SDK's result. `raise_for_error(response)` converts failures into typed errors.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx

from client.errors import error_for_status
from client.models import MapInfo, MapPage, Session, SessionPage, Trajectory, pose_to_list

API_PREFIX = "/v1"


@dataclass(frozen=True)
class Call:
    method: str
    path: str
    parse: Callable[[httpx.Response], Any]
    params: dict[str, Any] = field(default_factory=dict)
    json: Any = None
    content: bytes | None = None  # a binary body (with its content type in `headers`)
    headers: dict[str, str] = field(default_factory=dict)

    def request_options(self) -> dict[str, Any]:
        """The keyword arguments of httpx's `request` beside method and path."""
        return {"params": self.params or None, "json": self.json, "content": self.content,
                "headers": self.headers or None}


def raise_for_error(response: httpx.Response) -> None:
    """Raise the typed error carrying the server's message when `response` is not a success."""
    if response.is_success:
        return
    try:
        body: Any = response.json()
    except ValueError:
        body = response.text
    raise error_for_status(response.status_code, body, response.reason_phrase)


def _session_path(session_id: str, suffix: str = "") -> str:
    if not session_id or not isinstance(session_id, str):
        raise ValueError("a session id is required")
    return f"{API_PREFIX}/sessions/{quote(session_id, safe='')}{suffix}"


def _drop_none(values: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in values.items() if v is not None}


def intrinsics_payload(intrinsics: Any) -> dict[str, Any] | None:
    """{fx, fy, cx, cy, width?, height?, distortion?} from a dict, a worker.geometry.Intrinsics or a 4-sequence;
    `distortion` ({model, k1, k2, ...}: the lens, see openapi.yaml's DistortionIn) is passed on as given."""
    if intrinsics is None:
        return None
    if isinstance(intrinsics, dict):
        values = dict(intrinsics)
    elif hasattr(intrinsics, "fx"):
        keys = ("fx", "fy", "cx", "cy", "width", "height")
        values = {k: getattr(intrinsics, k) for k in keys if hasattr(intrinsics, k)}
    elif isinstance(intrinsics, Sequence) and len(intrinsics) == 4:
        values = dict(zip(("fx", "fy", "cx", "cy"), intrinsics))
    else:
        raise ValueError("intrinsics must be a dict, an Intrinsics or [fx, fy, cx, cy]")
    missing = {"fx", "fy", "cx", "cy"} - values.keys()
    if missing:
        raise ValueError(f"intrinsics lack {sorted(missing)}")
    out: dict[str, Any] = {}
    for key, value in values.items():
        if key in ("width", "height"):
            out[key] = int(value)
        elif key in ("fx", "fy", "cx", "cy"):
            out[key] = float(value)
        elif key == "distortion" and value is not None:
            out[key] = dict(value)
    if out["fx"] <= 0 or out["fy"] <= 0:
        raise ValueError("focal lengths must be positive")
    return out


def create_session(intrinsics: Any = None, preset: str | None = None, name: str | None = None,
                   device_id: str | None = None, metadata: dict[str, Any] | None = None,
                   pose_mode: str | None = None, skip_frames: bool | None = None,
                   tracking_side: int | None = None, frame_rate: float | None = None, map_id: str | None = None,
                   map_mode: str | None = None) -> Call:
    if map_mode is not None and map_mode not in MAP_MODES:
        raise ValueError(f"map_mode must be one of {', '.join(MAP_MODES)}, got {map_mode!r}")
    body = _drop_none({"intrinsics": intrinsics_payload(intrinsics), "preset": preset, "name": name,
                       "device_id": device_id, "metadata": metadata, "pose_mode": pose_mode,
                       "skip_frames": skip_frames, "tracking_side": tracking_side, "frame_rate": frame_rate,
                       "map_id": map_id, "map_mode": map_mode})
    return Call("POST", f"{API_PREFIX}/sessions", lambda r: Session.from_json(r.json()), json=body)


def list_sessions(status: str | None = None, device_id: str | None = None, name: str | None = None,
                  limit: int | None = None, cursor: str | None = None) -> Call:
    def parse(response: httpx.Response) -> SessionPage:
        data = response.json()
        return SessionPage([Session.from_json(s) for s in data.get("sessions", [])], data.get("next_cursor"))

    params = _drop_none({"status": status, "device_id": device_id, "name": name, "limit": limit, "cursor": cursor})
    return Call("GET", f"{API_PREFIX}/sessions", parse, params=params)


def get_session(session_id: str) -> Call:
    return Call("GET", _session_path(session_id), lambda r: Session.from_json(r.json()))


def delete_session(session_id: str) -> Call:
    return Call("DELETE", _session_path(session_id), lambda r: None)


def _check_which(which: str) -> str:
    if which not in ("all", "keyframes"):
        raise ValueError(f"which must be 'all' or 'keyframes', got {which!r}")
    return which


def trajectory(session_id: str, which: str = "all") -> Call:
    return Call("GET", _session_path(session_id, "/trajectory"), lambda r: Trajectory.from_json(r.json()),
                params={"format": "json", "which": _check_which(which)})


def presets() -> Call:
    return Call("GET", f"{API_PREFIX}/presets", lambda r: r.json())


def trajectory_tum(session_id: str, which: str = "all") -> Call:
    return Call("GET", _session_path(session_id, "/trajectory"), lambda r: r.text,
                params={"format": "tum", "which": _check_which(which)})


def render(session_id: str, pose: Any, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
           kind: str = "color", exposure_of: int | None = None) -> Call:
    if kind not in ("color", "depth"):
        raise ValueError(f"kind must be 'color' or 'depth', got {kind!r}")
    if width <= 0 or height <= 0:
        raise ValueError("width and height must be positive")
    if exposure_of is not None and exposure_of < 0:
        raise ValueError("exposure_of must be a frame's seq (>= 0)")
    params = {"pose": ",".join(repr(v) for v in pose_to_list(pose)), "width": int(width), "height": int(height),
              "fx": float(fx), "fy": float(fy), "cx": float(cx), "cy": float(cy), "kind": kind}
    if exposure_of is not None:
        params["exposure_of"] = int(exposure_of)
    return Call("GET", _session_path(session_id, "/render"), lambda r: r.content, params=params)


MAP_FORMATS = ("ply", "spz", "splat")


def map_ply(session_id: str, sh_degree: int = 0, format: str = "ply") -> Call:
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be within 0..3, got {sh_degree}")
    if format not in MAP_FORMATS:
        raise ValueError(f"format must be one of {', '.join(MAP_FORMATS)}, got {format!r}")
    if format == "ply":
        return Call("GET", _session_path(session_id, "/map.ply"), lambda r: r.content,
                    params={"sh_degree": sh_degree})
    return Call("GET", _session_path(session_id, "/map"), lambda r: r.content, params={"format": format})


MAP_MODES = ("localize", "extend")
MAP_FILE_FORMATS = ("package", *MAP_FORMATS)
MAP_PACKAGE_TYPE = "application/x-flashmono-map"


def _map_path(map_id: str, suffix: str = "") -> str:
    if not map_id or not isinstance(map_id, str):
        raise ValueError("a map id is required")
    return f"{API_PREFIX}/maps/{quote(map_id, safe='')}{suffix}"


def create_map(session_id: str, name: str) -> Call:
    _session_path(session_id)  # validates the id
    return Call("POST", f"{API_PREFIX}/maps", lambda r: MapInfo.from_json(r.json()),
                json={"session_id": session_id, "name": name})


def package_bytes(path_or_bytes: str | Path | bytes) -> bytes:
    """A map package's bytes: given, or read from a file."""
    if isinstance(path_or_bytes, bytes | bytearray | memoryview):
        return bytes(path_or_bytes)
    return Path(path_or_bytes).read_bytes()


def upload_map(package: bytes, name: str | None = None) -> Call:
    return Call("POST", f"{API_PREFIX}/maps", lambda r: MapInfo.from_json(r.json()), params=_drop_none({"name": name}),
                content=package, headers={"content-type": MAP_PACKAGE_TYPE})


def list_maps(limit: int | None = None, cursor: str | None = None) -> Call:
    def parse(response: httpx.Response) -> MapPage:
        data = response.json()
        return MapPage([MapInfo.from_json(m) for m in data.get("maps", [])], data.get("next_cursor"))

    return Call("GET", f"{API_PREFIX}/maps", parse, params=_drop_none({"limit": limit, "cursor": cursor}))


def get_map(map_id: str) -> Call:
    return Call("GET", _map_path(map_id), lambda r: MapInfo.from_json(r.json()))


def delete_map(map_id: str) -> Call:
    return Call("DELETE", _map_path(map_id), lambda r: None)


def map_file(map_id: str, format: str = "ply", version: int | None = None, sh_degree: int = 0) -> Call:
    """A saved map's file: its package ("package", to upload elsewhere) or its surfels as PLY, SPZ or .splat."""
    if format not in MAP_FILE_FORMATS:
        raise ValueError(f"format must be one of {', '.join(MAP_FILE_FORMATS)}, got {format!r}")
    if format == "package":
        return Call("GET", _map_path(map_id, "/export"), lambda r: r.content, params=_drop_none({"version": version}))
    return Call("GET", _map_path(map_id, "/map"), lambda r: r.content,
                params=_drop_none({"format": format, "version": version, "sh_degree": sh_degree or None}))


def health() -> Call:
    return Call("GET", "/healthz", lambda r: r.json())


def ready() -> Call:
    return Call("GET", "/readyz", lambda r: r.json())
