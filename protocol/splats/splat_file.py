"""The `.splat` layout of antimatter15's WebGL viewer, read by most web splat viewers (Spark, SuperSplat,
gsplat.js, the three.js viewers): no header, 32 bytes a splat, little endian -

    position  3 x float32     world coordinates, as the PLY stores them (no axis change)
    scale     3 x float32     standard deviations in metres (linear, not log)
    colour    4 x uint8       RGB (0.5 + C0 f_dc) and opacity, each x 255
    rotation  4 x uint8       the unit wxyz quaternion, q * 128 + 128

Splats keep the map's order (the viewer's incremental update relies on it; the original converter sorts by size
for progressive display).
"""

from __future__ import annotations

import numpy as np

from .arrays import SplatArrays

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
assert RECORD.itemsize == 32


def encode_splat(splats: SplatArrays) -> bytes:
    """The splats as a .splat file."""
    record = np.zeros(len(splats), dtype=RECORD)
    record["position"] = splats.means
    record["scale"] = splats.scales
    rgba = np.concatenate([splats.colors, splats.opacities[:, None]], axis=1).astype(np.float64)
    record["rgba"] = np.clip(np.rint(rgba * 255.0), 0, 255).astype(np.uint8)
    q = splats.quats.astype(np.float64)
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    record["rotation"] = np.clip(np.rint(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return record.tobytes()


def decode_splat(data: bytes) -> SplatArrays:
    """Read a .splat file."""
    if len(data) % RECORD.itemsize:
        raise ValueError(f".splat data must be a multiple of {RECORD.itemsize} bytes, got {len(data)}")
    record = np.frombuffer(data, dtype=RECORD)
    q = (record["rotation"].astype(np.float64) - 128.0) / 128.0
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    rgba = record["rgba"].astype(np.float32) / 255.0
    return SplatArrays(means=record["position"].astype(np.float32), scales=record["scale"].astype(np.float32),
                       quats=q.astype(np.float32), opacities=rgba[:, 3].copy(), colors=rgba[:, :3].copy())
