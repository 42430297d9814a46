"""The registration's state as msgpack-able values (numpy arrays allowed), and back: a session snapshot carries it.
Descriptors are kept in half precision (unit vectors: the matches they make are the same)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .config import PhotoRegistrationConfig
from .features import PhotoFeatures
from .incremental import IncrementalRegistration
from .reconstruction import RegisteredPhoto


def _features(f: PhotoFeatures) -> dict[str, Any]:
    return {"keypoints": f.keypoints, "descriptors": f.descriptors.astype(np.float16)}


def _load_features(d: dict[str, Any]) -> PhotoFeatures:
    return PhotoFeatures(np.asarray(d["keypoints"], np.float64).reshape(-1, 2),
                         np.asarray(d["descriptors"], np.float32).reshape(-1, 128))


def registration_state(r: IncrementalRegistration) -> dict[str, Any]:
    """Everything `load_registration` needs to continue."""
    slot, keypoint, point = r.map.observations()
    return {
        "K": r.K,
        "photos": [{"index": p.index, "pose": p.pose, **_features(p.features)} for p in r.map.photos],
        "points": r.map.points,
        "observations": np.stack([slot, keypoint, point]) if len(slot) else np.zeros((3, 0), np.int64),
        "waiting": [{"index": i, **_features(f)} for i, f in r.waiting],
        "unregistered": [{"index": i, **_features(f)} for i, f in r.unregistered],
        "globally_adjusted_at": r.globally_adjusted_at,
    }


def load_registration(state: dict[str, Any], config: PhotoRegistrationConfig) -> IncrementalRegistration:
    """The registration `registration_state` saved, with the session's settings."""
    r = IncrementalRegistration(np.asarray(state["K"], np.float64).reshape(3, 3), config)
    for p in state["photos"]:
        r.map.add_photo(RegisteredPhoto(int(p["index"]), _load_features(p),
                                        np.asarray(p["pose"], np.float64).reshape(4, 4)))
    r.map.add_points(np.asarray(state["points"], np.float64).reshape(-1, 3))
    slot, keypoint, point = np.asarray(state["observations"], np.int64).reshape(3, -1)
    for s in np.unique(slot):
        mine = slot == s
        r.map.observe(int(s), keypoint[mine], point[mine])
    r.waiting = [(int(w["index"]), _load_features(w)) for w in state["waiting"]]
    r.unregistered = [(int(w["index"]), _load_features(w)) for w in state["unregistered"]]
    r.globally_adjusted_at = int(state["globally_adjusted_at"])
    return r
