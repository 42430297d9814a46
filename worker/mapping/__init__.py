"""The 2DGS map engine: surfels, rasterizer, voxelization, fusion, refinement, loop correction, PLY."""

from .rasterize import RenderResult, rasterize
from .surfels import Surfels

__all__ = ["RenderResult", "Surfels", "rasterize"]
