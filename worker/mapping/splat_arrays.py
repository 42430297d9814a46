"""Gaussians as numpy arrays: moved to `protocol.splats.arrays` (torch-free, the gateway converts maps too);
re-exported here."""

from protocol.splats.arrays import FLAT_SCALE, SplatArrays, splat_arrays_from_ply

__all__ = ["FLAT_SCALE", "SplatArrays", "splat_arrays_from_ply"]
