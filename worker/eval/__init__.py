"""The paper's metrics (ATE after Sim(3) alignment, PSNR, SSIM, LPIPS when weights exist, depth L1, FPS),
trajectory I/O and paper-style tables."""

from worker.data.tum_trajectory import Trajectory, associate, associate_trajectories, format_tum, read_tum, write_tum

from .lpips import Lpips
from .metrics import (
    AteResult,
    DepthL1,
    RenderingScores,
    absolute_trajectory_error,
    alignment_transform,
    ate_rmse,
    depth_l1,
    end_to_end_fps,
    evaluate_renders,
    gaussian_count,
    non_keyframe_indices,
    psnr,
    ssim,
)
from .tables import all_tables, ate_table, depth_table, load_metrics, mapping_table

__all__ = [
    "AteResult", "DepthL1", "Lpips", "RenderingScores", "Trajectory", "absolute_trajectory_error",
    "alignment_transform", "all_tables", "associate", "associate_trajectories", "ate_rmse", "ate_table",
    "depth_l1", "depth_table", "end_to_end_fps", "evaluate_renders", "format_tum", "gaussian_count", "load_metrics",
    "mapping_table", "non_keyframe_indices", "psnr", "read_tum", "ssim", "write_tum",
]
