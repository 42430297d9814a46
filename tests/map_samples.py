"""Small synthetic map packages for the tests of the map package format, the gateway's map routes and the SDK."""

from __future__ import annotations

import cv2
import numpy as np

from protocol.map_package import MapKeyframe, MapPackage, encode_package
from protocol.splats.ply_records import write_vertex_records

WIDTH, HEIGHT = 32, 24
SURFEL_PROPERTIES = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                     "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def surfels_ply(count: int, keyframe_ids: list[int], seed: int = 0) -> bytes:
    """A Gaussian PLY of `count` random surfels in the engine's layout, bound in turn to `keyframe_ids`."""
    rng = np.random.default_rng(seed)
    record = np.zeros(count, dtype=[(n, "<f4") for n in SURFEL_PROPERTIES] + [("keyframe_id", "<i4")])
    for axis, name in enumerate("xyz"):
        record[name] = rng.normal(0.0, 1.0, count) + axis
    for name in ("f_dc_0", "f_dc_1", "f_dc_2", "opacity"):
        record[name] = rng.normal(0.0, 1.0, count)
    record["scale_0"] = record["scale_1"] = -4.0
    record["scale_2"] = -10.0
    record["rot_0"] = 1.0
    record["keyframe_id"] = np.resize(np.asarray(keyframe_ids, np.int32), count)
    return write_vertex_records(record)


def keyframe(kf_id: int, seed: int = 0, with_depth: bool = True) -> MapKeyframe:
    """A WIDTHxHEIGHT keyframe at x = kf_id / 10 with a random image and depth."""
    rng = np.random.default_rng(seed + kf_id)
    image = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    pose = np.eye(4)
    pose[0, 3] = kf_id / 10
    K = np.array([[30.0, 0.0, WIDTH / 2], [0.0, 30.0, HEIGHT / 2], [0.0, 0.0, 1.0]])
    depth = rng.uniform(0.5, 3.0, ((HEIGHT + 1) // 2, (WIDTH + 1) // 2)).astype(np.float16) if with_depth else None
    return MapKeyframe(id=kf_id, pose=pose, K=K, width=WIDTH, height=HEIGHT,
                       jpeg=cv2.imencode(".jpg", image)[1].tobytes(), depth=depth)


def synthetic_package(name: str = "synthetic", keyframes: int = 3, surfels: int = 200, seed: int = 0,
                      scale: str = "metric") -> MapPackage:
    ids = [2 * i for i in range(keyframes)]
    return MapPackage(name=name, keyframes=[keyframe(i, seed) for i in ids], surfels_ply=surfels_ply(surfels, ids,
                      seed), scale=scale, mode="rgbd", sessions=["s" * 32], created_at="2026-01-02T03:04:05.000+00:00")


def synthetic_package_bytes(**options) -> bytes:
    return encode_package(synthetic_package(**options))
