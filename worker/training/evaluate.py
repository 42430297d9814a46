"""Evaluate a frontend model against trajectory baselines: ATE, depth AbsRel and raw per-frame surfel PSNR.

The model runs through the SubmapTracker exactly as the SLAM engine feeds it (submaps of 8 frames with one frame of
overlap, hidden state re-initialised per submap), with no backend: no pose graph, no refinement. Baselines use
ground truth only to start: identity poses (the camera never moves) and constant velocity (the motion between the
first two ground-truth poses, repeated).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from worker.data.synthetic import default_intrinsics, is_held_out_seed
from worker.eval.metrics import absolute_trajectory_error, psnr

from .cache import render_window
from .clips import fit_frame


@dataclass
class EvalSequence:
    """A sequence at the model resolution: images uint8 [L,H,W,3], depths [L,H,W] metres (0 = invalid),
    gt c2w [L,4,4] float64, K [3,3]."""

    name: str
    images: np.ndarray
    depths: np.ndarray
    c2w: np.ndarray
    K: np.ndarray


def held_out_synthetic(count: int = 10, frames: int = 32, width: int = 224, height: int = 160,
                       path_frames: int = 64, first_seed: int = 10_000) -> list[EvalSequence]:
    """`count` held-out synthetic scenes (seeds from `first_seed`, all >= the held-out bound): the first `frames`
    frames of each camera path sampled at `path_frames` frames per loop."""
    seeds = list(range(first_seed, first_seed + count))
    if not all(is_held_out_seed(s) for s in seeds):
        raise ValueError(f"evaluation seeds must be held out (>= 10000), got {seeds[0]}..{seeds[-1]}")
    K = default_intrinsics(width, height).matrix().numpy()
    return [EvalSequence(f"synthetic-{s}", *render_window(s, path_frames, 0, frames, width, height), K)
            for s in seeds]


def dataset_sequence(path: str | Path, width: int = 224, height: int = 160, stride: int = 1,
                     max_frames: int | None = None) -> EvalSequence:
    """A dataset with depth and ground-truth poses (any format the frame sources read) fitted to width x height."""
    from worker.data import open_source

    images, depths, poses, K = [], [], [], None
    for frame in open_source(path, use_gt_depth=True, stride=stride, max_frames=max_frames):
        image, depth, intr = fit_frame(frame, width, height)
        images.append(image)
        depths.append(depth)
        poses.append(np.asarray(frame.gt_pose, dtype=np.float64))
        K = intr.matrix().numpy()
    if len(images) < 3:
        raise ValueError(f"{path}: need at least 3 frames with depth and poses, got {len(images)}")
    return EvalSequence(Path(str(path)).name, np.stack(images), np.stack(depths), np.stack(poses), K)


# ---- baselines and metrics ---------------------------------------------------------------------------------------
def identity_poses(gt_c2w: np.ndarray) -> np.ndarray:
    """The camera that never moves: every pose is the first ground-truth pose."""
    return np.repeat(gt_c2w[:1], len(gt_c2w), axis=0)


def constant_velocity_poses(gt_c2w: np.ndarray) -> np.ndarray:
    """T_k = T_0 (T_0^-1 T_1)^k: the motion between the first two ground-truth poses, repeated."""
    step = np.linalg.inv(gt_c2w[0]) @ gt_c2w[1]
    poses = [gt_c2w[0]]
    for _ in range(1, len(gt_c2w)):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def trajectory_ate(estimate_c2w: np.ndarray, gt_c2w: np.ndarray) -> float:
    """ATE RMSE after Sim(3) alignment of camera positions. A trajectory without spread (all positions equal)
    is aligned by the limit of Sim(3), scale 0: every position maps to the ground truth's centroid."""
    est = estimate_c2w[:, :3, 3]
    if np.ptp(est, axis=0).max() < 1e-9:
        ref = gt_c2w[:, :3, 3]
        return float(np.sqrt(((ref - ref.mean(axis=0)) ** 2).sum(axis=1).mean()))
    return absolute_trajectory_error(estimate_c2w, gt_c2w, align="sim3").rmse


def depth_abs_rel(pred_depth: np.ndarray, gt_depth: np.ndarray) -> float:
    """Mean |s p - g| / g over pixels with both depths valid, s = median(g) / median(p) (per-frame scale)."""
    valid = np.isfinite(pred_depth) & (pred_depth > 0) & (gt_depth > 0)
    if not valid.any():
        return math.nan
    p, g = pred_depth[valid].astype(np.float64), gt_depth[valid].astype(np.float64)
    s = np.median(g) / np.median(p)
    return float(np.mean(np.abs(s * p - g) / g))


def raw_surfel_psnr(surfels, image: np.ndarray, K: np.ndarray) -> float:
    """PSNR of one frame's own per-pixel surfels (tracker CameraSurfels, no refinement) rendered from its camera."""
    from worker.mapping import Surfels, rasterize

    H, W = image.shape[:2]
    n = H * W
    cloud = Surfels(means=surfels.points.reshape(n, 3).float(), quats=surfels.quats.reshape(n, 4).float(),
                    scales=surfels.scales.reshape(n, 2).float(), opacities=surfels.opacity.reshape(n).float(),
                    colors=surfels.colors.reshape(n, 3).float(), keyframe_ids=torch.zeros(n, dtype=torch.int64))
    with torch.no_grad():
        rendered = rasterize(cloud, torch.eye(4), torch.as_tensor(K, dtype=torch.float32), W, H)
    return psnr(rendered.rgb.clamp(0, 1).numpy(), image)


@dataclass
class SequenceScores:
    """One method on one sequence (NaN where a method has no such output)."""

    sequence: str
    method: str
    ate: float
    abs_rel: float = math.nan
    psnr: float = math.nan


def evaluate_baselines(seq: EvalSequence) -> list[SequenceScores]:
    """Identity and constant-velocity ATE on one sequence."""
    return [SequenceScores(seq.name, "identity", trajectory_ate(identity_poses(seq.c2w), seq.c2w)),
            SequenceScores(seq.name, "const-velocity", trajectory_ate(constant_velocity_poses(seq.c2w), seq.c2w))]


def evaluate_model(model, seq: EvalSequence, method: str = "model", submap_length: int = 8) -> SequenceScores:
    """Track the sequence with the model (submaps, no backend) and score poses, depth and raw surfels."""
    from worker.frontend.tracker import SubmapTracker, TrackerConfig
    from worker.geometry import Intrinsics

    model.eval()
    tracker = SubmapTracker(model, TrackerConfig(submap_length=submap_length))
    H, W = seq.images.shape[1:3]
    intr = Intrinsics.from_matrix(torch.as_tensor(seq.K), W, H)
    poses, rels, psnrs = [], [], []
    for i, image in enumerate(seq.images):
        chw = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
        tracked = tracker.track(i, chw, intr)
        poses.append(tracked.pose_world.numpy())
        rels.append(depth_abs_rel(tracked.surfels.points[..., 2].float().numpy(), seq.depths[i]))
        psnrs.append(raw_surfel_psnr(tracked.surfels, image, seq.K))
    finite = [r for r in rels if math.isfinite(r)]
    return SequenceScores(seq.name, method, trajectory_ate(np.stack(poses), seq.c2w),
                          float(np.mean(finite)) if finite else math.nan, float(np.mean(psnrs)))
