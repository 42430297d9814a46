"""The mapping stage's work items (keyframe jobs, pose updates) and the map it builds with the engine's settings.

Jobs are data (arrays and numbers, no closures): a snapshot can carry the ones still waiting, and any process can
build them. The stage itself (its queue, thread and load shedding) is worker.pipeline.mapping_stage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from worker.config import MappingConfig


@dataclass
class StereoViews:
    """What a keyframe's multi-view depth is estimated from, as plain data: the keyframe's image (uint8 [H,W,3]),
    K, camera pose (SE(3) c2w) and world scale (Sim(3) poses: depth is divided by it), the kept frames' images and
    poses, and the depth hint of the pose source (sweep range, typical depth), when it gave one."""

    image: np.ndarray
    K: np.ndarray
    pose: np.ndarray
    scale: float
    images: list[np.ndarray]
    poses: list[np.ndarray]
    depth_range: tuple[float, float] | None
    scene_depth: float | None

    def state_dict(self) -> dict[str, Any]:
        return {"image": self.image, "K": self.K, "pose": self.pose, "scale": self.scale, "images": self.images,
                "poses": self.poses, "depth_range": self.depth_range, "scene_depth": self.scene_depth}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> StereoViews:
        return cls(np.asarray(state["image"], np.uint8), np.asarray(state["K"], np.float64),
                   np.asarray(state["pose"], np.float64), float(state["scale"]),
                   [np.asarray(i, np.uint8) for i in state["images"]],
                   [np.asarray(q, np.float64) for q in state["poses"]],
                   None if state["depth_range"] is None else tuple(state["depth_range"]), state["scene_depth"])


@dataclass
class KeyframeJob:
    """One keyframe for the map: pose c2w (Sim(3)), K at the grid's resolution, image float [H,W,3] in [0,1],
    the per-pixel camera-frame surfel grid (see worker.pipeline.surfel_init) and the depth used to check renders.

    An empty `grid` is built in the mapping stage: from `views` (multi-view stereo, worker.pipeline.depth_sources.
    multiview) or else from `depth` (the sensor's). `query_loops`: the built keyframe goes on to loop closing."""

    kf_id: int
    pose: np.ndarray
    K: torch.Tensor | None
    image: torch.Tensor
    grid: dict[str, torch.Tensor] = field(default_factory=dict)
    depth: torch.Tensor | None = None
    views: StereoViews | None = None
    query_loops: bool = False

    @property
    def built(self) -> bool:
        return bool(self.grid)

    def state_dict(self) -> dict[str, Any]:
        """The job as plain data (arrays stay arrays: see protocol.codec)."""
        return {"kf_id": self.kf_id, "pose": self.pose, "K": self.K, "image": self.image, "grid": self.grid,
                "depth": self.depth, "views": None if self.views is None else self.views.state_dict(),
                "query_loops": self.query_loops}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> KeyframeJob:
        def tensor(value: Any) -> torch.Tensor | None:
            return None if value is None else torch.from_numpy(np.array(value))

        return cls(int(state["kf_id"]), np.asarray(state["pose"], np.float64), tensor(state["K"]),
                   tensor(state["image"]), {k: tensor(v) for k, v in (state.get("grid") or {}).items()},
                   tensor(state.get("depth")),
                   None if state.get("views") is None else StereoViews.from_state(state["views"]),
                   bool(state.get("query_loops", False)))


@dataclass
class PoseUpdateJob:
    poses: dict[int, np.ndarray]


def job_state(job: KeyframeJob | PoseUpdateJob) -> dict[str, Any]:
    """A mapping job as plain data (snapshots, the mapping process's wire): `job_from_state` reads it."""
    if isinstance(job, KeyframeJob):
        return {"keyframe": job.state_dict()}
    return {"poses": [[k, v] for k, v in job.poses.items()]}


def job_from_state(item: dict[str, Any]) -> KeyframeJob | PoseUpdateJob:
    """The job `job_state` made `item` from."""
    if "keyframe" in item:
        return KeyframeJob.from_state(item["keyframe"])
    return PoseUpdateJob({int(k): np.asarray(v, np.float64) for k, v in item["poses"]})


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
