"""An `extend` session's map joined to the stored map it ran in: a new version of that map.

By the session's end its keyframes and surfels are in the map's world already (its anchoring moved them there). The
new version keeps every keyframe and surfel of the stored map and adds the session's: its keyframes under ids after
the map's (the surfels' keyframe ids follow), and its surfels where the map has none yet, so a place seen by both
keeps the map's surfels once (occupancy on a voxel grid of the map's voxel size).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from protocol.map_package import MapPackage
from protocol.splats.ply_records import read_vertex_records, write_vertex_records

# Without a voxel size in the map (a map built without fusion), occupancy is judged on cells this share of the
# map's bounds diagonal.
FALLBACK_VOXEL_SHARE = 0.005


def merge_packages(base: MapPackage, addition: MapPackage, session_id: str) -> MapPackage:
    """`base` extended by `addition` (see the module docstring), made by session `session_id`."""
    offset = max(kf.id for kf in base.keyframes) + 1 - min(kf.id for kf in addition.keyframes)
    keyframes = base.keyframes + [replace(kf, id=kf.id + offset) for kf in addition.keyframes]
    old = read_vertex_records(base.surfels_ply)
    new = read_vertex_records(addition.surfels_ply)
    if "keyframe_id" in (new.dtype.names or ()):
        new = new.copy()
        new["keyframe_id"] = np.where(new["keyframe_id"] >= 0, new["keyframe_id"] + offset, new["keyframe_id"])
    new = new[~_occupied(_centres(old), _centres(new), _voxel_size(base, old))]
    surfels = write_vertex_records(_concatenated(old, new)) if len(new) else base.surfels_ply
    sessions = list(dict.fromkeys([*base.sessions, *addition.sessions, session_id]))
    return replace(base, keyframes=keyframes, surfels_ply=surfels, sessions=sessions, created_at="")


def _centres(records: np.ndarray) -> np.ndarray:
    return np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float64)


def _voxel_size(package: MapPackage, records: np.ndarray) -> float:
    size = package.engine.get("voxel_size")
    if size:
        return float(size)
    centres = _centres(records)
    if not len(centres):
        return 1.0
    low, high = np.percentile(centres, [1, 99], axis=0)
    return max(float(np.linalg.norm(high - low)) * FALLBACK_VOXEL_SHARE, 1e-6)


def _occupied(old: np.ndarray, new: np.ndarray, voxel: float) -> np.ndarray:
    """For each point of `new`, whether a point of `old` lies in its voxel."""
    if not len(old) or not len(new):
        return np.zeros(len(new), bool)
    cells = {tuple(c) for c in np.floor(old / voxel).astype(np.int64)}
    return np.array([tuple(c) in cells for c in np.floor(new / voxel).astype(np.int64)], bool)


def _concatenated(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """The two record arrays as one, in the first's layout (a column it lacks is dropped from the second)."""
    names = old.dtype.names or ()
    out = np.empty(len(old) + len(new), old.dtype)
    out[: len(old)] = old
    for name in names:
        out[name][len(old):] = new[name]
    return out
