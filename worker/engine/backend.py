"""The mapping stage's work items (keyframe jobs, pose updates) and the map it builds with the engine's settings.

The stage itself (its queue, thread and load shedding) is worker.engine.mapping_stage.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from worker.config import MappingConfig


@dataclass
class KeyframeJob:
    """One keyframe for the map: pose c2w (Sim(3)), K at the grid's resolution, image float [H,W,3] in [0,1],
    the per-pixel camera-frame surfel grid (see worker.engine.surfel_init) and the depth used to check renders, or
    `build`, which makes both in the backend thread."""

    kf_id: int
    pose: np.ndarray
    K: torch.Tensor | None  # None until `build` has run
    image: torch.Tensor
    grid: dict[str, torch.Tensor]
    depth: torch.Tensor | None = None
    # Builds (K, grid, depth) in the backend thread: costly ones (multi-view depth), or ones that need what is
    # known only later (the camera of a session whose focal length is being estimated).
    build: Callable[[], tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor | None]] | None = None


@dataclass
class PoseUpdateJob:
    poses: dict[int, np.ndarray]


def fusion_thresholds(cfg: MappingConfig, prune: bool):
    """The map's fusion thresholds: `cfg`'s pruning errors when `prune`, else none that prunes."""
    from worker.mapping.fusion import FusionThresholds

    return FusionThresholds(rgb_error=cfg.prune_rgb_error if prune else math.inf,
                            depth_error=cfg.prune_depth_error if prune else math.inf, tau_accum=cfg.tau_accum)


def build_gaussian_map(cfg: MappingConfig, device: str):
    """The map object with this engine's mapping settings."""
    from worker.mapping.gaussian_map import GaussianMap, MapConfig
    from worker.mapping.hole_closing import HoleClosingSettings
    from worker.mapping.refine import RefineSettings

    return GaussianMap(MapConfig(
        window=cfg.refine_keyframes,
        iterations=cfg.refine_iterations,
        thresholds=fusion_thresholds(cfg, cfg.prune),
        refine=RefineSettings(lambda_ssim=cfg.ssim_weight, lambda_depth=cfg.depth_weight, exposure=cfg.exposure,
                              exposure_prior=cfg.exposure_prior, exposure_threshold=cfg.exposure_threshold,
                              exposure_shared=cfg.exposure_channels == "shared"),
        archived_images=cfg.archived_images,
        archived_views_per_refine=cfg.archived_views_per_refine,
        voxel_cap=cfg.voxel_cap,
        final_refine_budget_s=cfg.final_refine_budget_s or None,
        final_refine_lr_end=cfg.final_refine_lr_end,
        hole_closing=HoleClosingSettings(margin=cfg.hole_margin) if cfg.close_holes else None,
        device=device,
    ))


def unmerged_surfels(grid: dict[str, torch.Tensor], kf_id: int):
    """All valid per-pixel surfels, no voxelization (voxel_block = 1)."""
    from worker.mapping.surfels import Surfels
    from worker.mapping.voxelize import VoxelizedSurfels

    v = grid["valid"]
    rows, cols = torch.nonzero(v, as_tuple=True)
    surfels = Surfels(means=grid["means"][v], quats=grid["quats"][v], scales=grid["scales"][v],
                      opacities=grid["opacities"][v], colors=grid["colors"][v],
                      keyframe_ids=torch.full((int(v.sum()),), kf_id, dtype=torch.int64))
    return VoxelizedSurfels(surfels, torch.stack([rows, cols], -1), torch.zeros(len(surfels), dtype=torch.bool))
