"""The 2DGS map engine: surfels, rasterizer, voxelization, fusion, refinement, loop correction, PLY."""

from .fusion import FusionThresholds
from .gaussian_map import FusionStats, GaussianMap, MapConfig
from .loop_correction import apply_keyframe_deltas, correct_map, pose_deltas
from .ply import read_ply, surfels_from_ply_bytes, surfels_to_ply_bytes, write_ply
from .rasterize import RenderResult, rasterize
from .refine import RefineSettings, RefineView, refine_surfels
from .surfels import Surfels
from .voxelize import VoxelizedSurfels, valid_pixel_mask, voxelize

__all__ = ["RenderResult", "Surfels", "rasterize"]
__all__ += [
    "FusionStats", "FusionThresholds", "GaussianMap", "MapConfig", "RefineSettings", "RefineView", "VoxelizedSurfels",
    "apply_keyframe_deltas", "correct_map", "pose_deltas", "read_ply", "refine_surfels", "surfels_from_ply_bytes",
    "surfels_to_ply_bytes", "valid_pixel_mask", "voxelize", "write_ply",
]
