"""The map package: a session's map as one file, format `flashmono.map/1`, to save, export, upload and start new
sessions in (torch-free: the gateway validates what it stores, the workers build and load it).

One msgpack document (protocol.codec: arrays as raw bytes + dtype + shape):

    {"format": "flashmono.map/1",
     "meta": {"name", "surfels", "keyframes", "bounds", "scale", "camera", "mode", "sessions", "created_at"},
     "keyframes": [{"id": int, "pose": float64 [4, 4] camera-to-world (a similarity [sR|t] in up-to-scale maps),
                    "K": float64 [3, 3], "width": int, "height": int, "jpeg": bytes (the RGB image),
                    "depth": float16 [ceil(H/2), ceil(W/2)] camera-frame z in map units (0/NaN: none) or None,
                    "exposure": float32 [6] or None (optional: per-channel gain and bias, worker.mapping.exposure),
                    "rendered": bool (optional: image and depth are the map's render at the pose, the engine no
                    longer held the photo),
                    "places": {"keypoints": float32 [n, 2], "descriptors": uint8 [n, 32] (ORB), "points": float64
                    [n, 3] (the keypoints' world points), "bag": float32 [words] (their bag of words)} or None
                    (optional: what relocalizing in the map needs of the keyframe, made when it was packaged)},
                    ...],
     "surfels_ply": bytes (the engine's binary Gaussian PLY, SH degree 0, with its int32 `keyframe_id` column: each
                    surfel moves with its keyframe),
     "engine": {"voxel_size": float or None, "background": None or {"face_cells": n, "rgb": uint8 [6, n, n, 3],
                "seen": bool [6, n, n]}} (optional: what the engine needs to go on mapping as the session did)}

`meta` is what listings show: `surfels`, `keyframes`, `bounds` (the 1st-99th percentile box of the surfel centres:
{"min": [x, y, z], "max": [x, y, z]}, null without surfels) and `camera` ({width, height, fx, fy, cx, cy} of the
first keyframe) are computed from the content, on encode and again on decode (never trusted from the file);
`name`, `scale` ("metric" or "up_to_scale"), `mode` (the building session's input mode: rgbd, posed-rgbd,
posed-rgb, rgb), `sessions` (the ids of the sessions that built it) and `created_at` (ISO 8601) are carried.
`decode_package` refuses anything else with a `MapPackageError` saying why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Literal, get_args

import numpy as np

from protocol.codec import pack, unpack
from protocol.image_header import image_size
from protocol.limits import MAX_IMAGE_SIDE, MAX_MAP_KEYFRAMES, MAX_MAP_PACKAGE_BYTES
from protocol.splats.ply_records import read_gaussian_records

FORMAT = "flashmono.map/1"
CONTENT_TYPE = "application/x-flashmono-map"
FILE_SUFFIX = ".fmap"
MapScale = Literal["metric", "up_to_scale"]
SCALES: tuple[str, ...] = get_args(MapScale)
BOUNDS_PERCENTILES = (1.0, 99.0)
MAX_TEXT = 200  # characters of a name, a mode, a session id, a timestamp
EXPOSURE_SIZE = 6
# A keyframe's places (optional): what relocalizing in the map needs of it, made once when the map is packaged
PLACE_FIELDS = ("keypoints", "descriptors", "points", "bag")
MAX_PLACE_POINTS = 20_000
MAX_PLACE_WORDS = 1 << 20


class MapPackageError(ValueError):
    """Bytes that are no valid map package; the message says what is wrong."""


@dataclass
class MapKeyframe:
    """One keyframe of a map (see the module docstring for each field)."""

    id: int
    pose: np.ndarray
    K: np.ndarray
    width: int
    height: int
    jpeg: bytes
    depth: np.ndarray | None = None
    exposure: np.ndarray | None = None
    rendered: bool = False
    places: dict[str, np.ndarray] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "pose": self.pose, "K": self.K, "width": self.width, "height": self.height,
                "jpeg": self.jpeg, "depth": self.depth, "exposure": self.exposure, "rendered": self.rendered,
                "places": self.places}


@dataclass
class MapPackage:
    """A map: its keyframes, its surfels (binary Gaussian PLY) and what describes it."""

    name: str
    keyframes: list[MapKeyframe]
    surfels_ply: bytes
    scale: str = "up_to_scale"
    mode: str = "unknown"
    sessions: list[str] = field(default_factory=list)
    created_at: str = ""
    engine: dict[str, Any] = field(default_factory=dict)

    def meta(self) -> dict[str, Any]:
        """The package's metadata (module docstring), the counts, bounds and camera computed from the content."""
        first = self.keyframes[0]
        camera = {"width": first.width, "height": first.height, "fx": float(first.K[0, 0]),
                  "fy": float(first.K[1, 1]), "cx": float(first.K[0, 2]), "cy": float(first.K[1, 2])}
        records = read_gaussian_records(self.surfels_ply)
        return {"name": self.name, "surfels": len(records), "keyframes": len(self.keyframes),
                "bounds": _bounds(records), "scale": self.scale, "camera": camera, "mode": self.mode,
                "sessions": list(self.sessions), "created_at": self.created_at}


def encode_package(package: MapPackage) -> bytes:
    """The package as `flashmono.map/1` bytes (`created_at` is set to now when empty); MapPackageError when it is
    not one `decode_package` would take back."""
    if not package.created_at:
        package = replace(package, created_at=datetime.now(UTC).isoformat(timespec="milliseconds"))
    _check(package)
    return pack({"format": FORMAT, "meta": package.meta(),
                 "keyframes": [kf.to_dict() for kf in package.keyframes], "surfels_ply": package.surfels_ply,
                 "engine": package.engine})


def decode_package(data: bytes, max_bytes: int = MAX_MAP_PACKAGE_BYTES) -> MapPackage:
    """The package in `data`, every field checked; MapPackageError (a ValueError) on anything corrupt."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise MapPackageError(f"a map package is bytes, not {type(data).__name__}")
    if len(data) > max_bytes:
        raise MapPackageError(f"the package is {len(data)} bytes, over the limit of {max_bytes}")
    try:
        doc = unpack(bytes(data))
    except ValueError as err:
        raise MapPackageError(f"not a map package (msgpack): {err}") from err
    if not isinstance(doc, dict):
        raise MapPackageError("not a map package: the document is not a map")
    if doc.get("format") != FORMAT:
        raise MapPackageError(f"not a map package: format {doc.get('format')!r}, expected {FORMAT!r}")
    meta = _get(doc, "meta", dict, "package")
    keyframes = _get(doc, "keyframes", list, "package")
    if len(keyframes) > MAX_MAP_KEYFRAMES:
        raise MapPackageError(f"the package has {len(keyframes)} keyframes, over the limit of {MAX_MAP_KEYFRAMES}")
    package = MapPackage(
        name=_text(meta, "name", "meta"), keyframes=[_keyframe(kf, i) for i, kf in enumerate(keyframes)],
        surfels_ply=_get(doc, "surfels_ply", bytes, "package"), scale=_text(meta, "scale", "meta"),
        mode=_text(meta, "mode", "meta", "unknown"), sessions=_texts(meta, "sessions", "meta"),
        created_at=_text(meta, "created_at", "meta", ""), engine=_engine(doc.get("engine")))
    _check(package)
    return package


def package_meta(data: bytes) -> dict[str, Any]:
    """The metadata of the package in `data` (decoded and checked whole: MapPackageError when corrupt)."""
    return decode_package(data).meta()


# --- checks -----------------------------------------------------------------------------------------------------
def _check(package: MapPackage) -> None:
    """What every package holds: keyframes with unique ids, a known scale, readable finite surfels bound to them."""
    if not package.keyframes:
        raise MapPackageError("the package has no keyframes")
    if package.scale not in SCALES:
        raise MapPackageError(f"meta.scale must be one of {SCALES}, got {package.scale!r}")
    ids = [kf.id for kf in package.keyframes]
    if len(set(ids)) != len(ids):
        raise MapPackageError("two keyframes share an id")
    for kf in package.keyframes:
        _check_keyframe(kf)
    try:
        records = read_gaussian_records(package.surfels_ply)
    except ValueError as err:
        raise MapPackageError(f"surfels_ply: {err}") from err
    names = records.dtype.names or ()
    if any(records.dtype[n].kind == "f" and not np.isfinite(records[n]).all() for n in names):
        raise MapPackageError("surfels_ply: the surfels hold non-finite values")
    if "keyframe_id" in names and not np.isin(records["keyframe_id"], [*ids, -1]).all():
        raise MapPackageError("surfels_ply: surfels are bound to keyframes the package does not have")


def _check_keyframe(kf: MapKeyframe) -> None:
    where = f"keyframe {kf.id}"
    if not (0 < kf.width <= MAX_IMAGE_SIDE and 0 < kf.height <= MAX_IMAGE_SIDE):
        raise MapPackageError(f"{where}: size {kf.width}x{kf.height} is out of range")
    pose = _array(kf.pose, "float64", (4, 4), f"{where}: pose")
    if not np.isfinite(pose).all() or not np.allclose(pose[3], [0, 0, 0, 1]) or np.linalg.det(pose[:3, :3]) <= 0:
        raise MapPackageError(f"{where}: the pose is not a finite camera-to-world similarity [sR|t; 0 0 0 1]")
    K = _array(kf.K, "float64", (3, 3), f"{where}: K")
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise MapPackageError(f"{where}: K is not a finite camera matrix with positive focal lengths")
    try:
        kind, width, height = image_size(kf.jpeg)
    except ValueError as err:
        raise MapPackageError(f"{where}: the image is no JPEG ({err})") from err
    if kind != "jpeg" or (width, height) != (kf.width, kf.height):
        raise MapPackageError(f"{where}: the image is a {width}x{height} {kind}, not a {kf.width}x{kf.height} JPEG")
    if kf.depth is not None:
        _array(kf.depth, "float16", ((kf.height + 1) // 2, (kf.width + 1) // 2), f"{where}: depth")
    if kf.exposure is not None:
        exposure = _array(kf.exposure, "float32", (EXPOSURE_SIZE,), f"{where}: exposure")
        if not np.isfinite(exposure).all():
            raise MapPackageError(f"{where}: the exposure is not finite")
    if kf.places is not None:
        _check_places(kf.places, where)


def _check_places(places: Any, where: str) -> None:
    """A keyframe's places: its corners that have a depth (keypoints, ORB descriptors, world points) and its bag
    of words, all consistent and finite."""
    if not isinstance(places, dict) or set(places) != set(PLACE_FIELDS):
        raise MapPackageError(f"{where}: 'places' must hold exactly {', '.join(PLACE_FIELDS)}")
    n = places["keypoints"].shape[0] if isinstance(places["keypoints"], np.ndarray) else -1
    if not 0 <= n <= MAX_PLACE_POINTS:
        raise MapPackageError(f"{where}: places must have 0..{MAX_PLACE_POINTS} keypoints")
    _array(places["keypoints"], "float32", (n, 2), f"{where}: places keypoints")
    _array(places["descriptors"], "uint8", (n, 32), f"{where}: places descriptors")
    _array(places["points"], "float64", (n, 3), f"{where}: places points")
    bag = places["bag"]
    if not isinstance(bag, np.ndarray) or bag.dtype != np.float32 or bag.ndim != 1 or bag.size > MAX_PLACE_WORDS:
        raise MapPackageError(f"{where}: places bag must be a float32 vector of at most {MAX_PLACE_WORDS} words")
    if not (np.isfinite(places["keypoints"]).all() and np.isfinite(places["points"]).all()
            and np.isfinite(bag).all()):
        raise MapPackageError(f"{where}: places are not finite")


def _bounds(records: np.ndarray) -> dict[str, list[float]] | None:
    if len(records) == 0:
        return None
    centres = np.stack([np.asarray(records[k], np.float64) for k in ("x", "y", "z")], axis=1)
    low, high = np.percentile(centres, BOUNDS_PERCENTILES, axis=0)
    return {"min": [float(v) for v in low], "max": [float(v) for v in high]}


# --- reading the document ---------------------------------------------------------------------------------------
def _get(d: dict, key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in d:
        raise MapPackageError(f"{where}: '{key}' is missing")
    value = d[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise MapPackageError(f"{where}: '{key}' has the wrong type ({type(value).__name__})")
    return value


def _text(d: dict, key: str, where: str, default: str | None = None) -> str:
    if default is not None and d.get(key) is None:
        return default
    value = _get(d, key, str, where)
    if len(value) > MAX_TEXT:
        raise MapPackageError(f"{where}: '{key}' is longer than {MAX_TEXT} characters")
    return value


def _texts(d: dict, key: str, where: str) -> list[str]:
    values = d.get(key) or []
    if not isinstance(values, list) or len(values) > MAX_MAP_KEYFRAMES:
        raise MapPackageError(f"{where}: '{key}' must be a list of strings")
    return [_text({key: v}, key, where) for v in values]


def _array(value: Any, dtype: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    if not isinstance(value, np.ndarray) or value.dtype != np.dtype(dtype) or value.shape != shape:
        got = f"{value.dtype} {list(value.shape)}" if isinstance(value, np.ndarray) else type(value).__name__
        raise MapPackageError(f"{where} must be a {dtype} array of shape {list(shape)}, got {got}")
    return value


def _optional_array(d: dict, key: str) -> np.ndarray | None:
    value = d.get(key)
    if value is not None and not isinstance(value, np.ndarray):
        raise MapPackageError(f"'{key}' must be an array or null, got {type(value).__name__}")
    return value


def _keyframe(d: Any, index: int) -> MapKeyframe:
    if not isinstance(d, dict):
        raise MapPackageError(f"keyframe #{index} is not a map")
    where = f"keyframe #{index}"
    kf_id = _get(d, "id", int, where)
    if not -(2**62) < kf_id < 2**62:
        raise MapPackageError(f"{where}: id {kf_id} is out of range")
    rendered = d.get("rendered", False)
    if not isinstance(rendered, bool):
        raise MapPackageError(f"{where}: 'rendered' must be a boolean")
    return MapKeyframe(id=kf_id, pose=_get(d, "pose", np.ndarray, where), K=_get(d, "K", np.ndarray, where),
                       width=_get(d, "width", int, where), height=_get(d, "height", int, where),
                       jpeg=_get(d, "jpeg", bytes, where), depth=_optional_array(d, "depth"),
                       exposure=_optional_array(d, "exposure"), rendered=rendered, places=d.get("places"))


def _engine(d: Any) -> dict[str, Any]:
    """The optional engine hints, checked: voxel_size (positive finite or null), background (cube map or null)."""
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise MapPackageError("'engine' must be a map")
    voxel_size = d.get("voxel_size")
    if voxel_size is not None and (not isinstance(voxel_size, int | float) or isinstance(voxel_size, bool)
                                   or not math.isfinite(voxel_size) or voxel_size <= 0):
        raise MapPackageError("engine.voxel_size must be a positive number or null")
    background = d.get("background")
    if background is not None:
        if not isinstance(background, dict):
            raise MapPackageError("engine.background must be a map or null")
        cells = _get(background, "face_cells", int, "engine.background")
        if not 0 < cells <= 512:
            raise MapPackageError("engine.background.face_cells is out of range")
        _array(background.get("rgb"), "uint8", (6, cells, cells, 3), "engine.background.rgb")
        _array(background.get("seen"), "bool", (6, cells, cells), "engine.background.seen")
    return {"voxel_size": voxel_size, "background": background}
