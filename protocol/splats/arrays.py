"""Gaussians as plain numpy arrays with activated values: the common ground of the web map formats (SPZ, .splat).

Read from the map's PLY (3DGS/2DGS property layout, see `ply_records.py`) with numpy alone, so a format conversion costs
milliseconds and no torch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ply_records import FLAT_LOG_SCALE, SH_C0, read_gaussian_records

FLAT_SCALE = 0.0  # the third scale of a 2D surfel: a flat Gaussian (the PLY's stand-in, exp(-10) m, reads as this)


@dataclass(frozen=True)
class SplatArrays:
    """N Gaussians. means [N,3] float32 world positions; scales [N,3] float32 standard deviations in metres (the
    third is zero or tiny for 2D surfels); quats [N,4] float32 unit wxyz rotations (the scale axes are the columns
    of the rotation); opacities [N] float32 in [0,1]; colors [N,3] float32 RGB (degree-0 SH: 0.5 + C0 f_dc, not
    clipped)."""

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.means)
        shapes = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "colors": (n, 3)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"SplatArrays.{name} must have shape {shape}, got {getattr(self, name).shape}")

    def __len__(self) -> int:
        return len(self.means)

    @property
    def f_dc(self) -> np.ndarray:
        """The degree-0 SH coefficients (what 3DGS files store for colour)."""
        return (self.colors - 0.5) / SH_C0


def splat_arrays_from_ply(data: bytes) -> SplatArrays:
    """The Gaussians of a binary little-endian Gaussian PLY (our map export or any 3DGS/2DGS trainer's)."""
    v = read_gaussian_records(data)
    names = set(v.dtype.names or ())

    def stack(*keys: str) -> np.ndarray:
        return np.stack([np.asarray(v[k], dtype=np.float64) for k in keys], axis=-1)

    quats = stack("rot_0", "rot_1", "rot_2", "rot_3")
    norm = np.linalg.norm(quats, axis=-1, keepdims=True)
    quats = np.where(norm > 1e-12, quats / np.maximum(norm, 1e-12), [1.0, 0.0, 0.0, 0.0])
    scales = np.exp(stack("scale_0", "scale_1", *(["scale_2"] if "scale_2" in names else [])))
    if scales.shape[1] == 2:
        scales = np.concatenate([scales, np.full((len(scales), 1), FLAT_SCALE)], axis=1)
    else:  # a 2D surfel written for 3DGS readers: exactly flat again (renderers such as Spark draw zero as 2D)
        scales[np.asarray(v["scale_2"]) <= FLAT_LOG_SCALE + 1e-4, 2] = FLAT_SCALE
    return SplatArrays(
        means=stack("x", "y", "z").astype(np.float32),
        scales=scales.astype(np.float32),
        quats=quats.astype(np.float32),
        opacities=(1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], dtype=np.float64)))).astype(np.float32),
        colors=(0.5 + SH_C0 * stack("f_dc_0", "f_dc_1", "f_dc_2")).astype(np.float32),
    )
