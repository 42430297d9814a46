"""The 2DGS map engine: surfels, rasterizer, voxelization, fusion, refinement, loop correction, PLY."""

from .surfels import Surfels

__all__ = ["Surfels"]
