"""Evaluate a frontend model against trajectory baselines: ATE, depth AbsRel and raw per-frame surfel PSNR.

The model runs through the SubmapTracker exactly as the SLAM engine feeds it (submaps of 8 frames with one frame of
overlap, hidden state re-initialised per submap), with no backend: no pose graph, no refinement. ATE is scored for
both of the tracker's pose sources (the pose head, and the rigid fit between each frame's two point maps) from one
pass of the model. Two appearance figures: each frame's raw surfels rendered from its own camera (own view), and
frame t's raw surfels rendered at frame t+1's ground-truth relative pose against frame t+1's image (next view; the
surfels are brought to metric scale by the per-frame median depth ratio first). Baselines use ground truth only to
start: identity poses (the camera never moves) and constant velocity (the motion between the first two
ground-truth poses, repeated).
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


def _surfel_cloud(surfels, scale: float = 1.0):
    """Tracker CameraSurfels [H,W,...] as a flat Surfels cloud in the camera frame, means and sizes times `scale`."""
    from worker.mapping import Surfels

    n = surfels.points.shape[0] * surfels.points.shape[1]
    return Surfels(means=surfels.points.reshape(n, 3).float() * scale, quats=surfels.quats.reshape(n, 4).float(),
                   scales=surfels.scales.reshape(n, 2).float() * scale, opacities=surfels.opacity.reshape(n).float(),
                   colors=surfels.colors.reshape(n, 3).float(), keyframe_ids=torch.zeros(n, dtype=torch.int64))


def raw_surfel_psnr(surfels, image: np.ndarray, K: np.ndarray) -> float:
    """PSNR of one frame's own per-pixel surfels (tracker CameraSurfels, no refinement) rendered from its camera."""
    from worker.mapping import rasterize

    H, W = image.shape[:2]
    with torch.no_grad():
        rendered = rasterize(_surfel_cloud(surfels), torch.eye(4), torch.as_tensor(K, dtype=torch.float32), W, H)
    return psnr(rendered.rgb.clamp(0, 1).numpy(), image)


def next_view_psnr(surfels, gt_depth: np.ndarray, cam_to_next: np.ndarray, next_image: np.ndarray,
                   K: np.ndarray) -> float:
    """PSNR of one frame's raw surfels rendered at the next frame's camera against the next frame's image.

    The surfels (model units) are scaled to metres by median(gt depth) / median(predicted depth) over this frame's
    valid pixels, then seen through `cam_to_next` (ground-truth [4,4] mapping this camera's frame to the next's).
    Pixels the frame does not cover render as background and count. NaN when no pixel has both depths.
    """
    from worker.mapping import rasterize

    pred = surfels.points[..., 2].float().numpy()
    valid = np.isfinite(pred) & (pred > 0) & (gt_depth > 0)
    if not valid.any():
        return math.nan
    scale = float(np.median(gt_depth[valid]) / np.median(pred[valid]))
    H, W = next_image.shape[:2]
    with torch.no_grad():
        rendered = rasterize(_surfel_cloud(surfels, scale), torch.as_tensor(cam_to_next, dtype=torch.float32),
                             torch.as_tensor(K, dtype=torch.float32), W, H)
    return psnr(rendered.rgb.clamp(0, 1).numpy(), next_image)


@dataclass
class SequenceScores:
    """One method on one sequence (NaN where a method has no such output)."""

    sequence: str
    method: str
    ate: float  # poses from the pose head (the only poses of a baseline)
    abs_rel: float = math.nan
    psnr: float = math.nan  # own view
    psnr_next: float = math.nan  # next view
    ate_pointmap: float = math.nan  # poses from the point-map fit


def evaluate_baselines(seq: EvalSequence) -> list[SequenceScores]:
    """Identity and constant-velocity ATE on one sequence."""
    return [SequenceScores(seq.name, "identity", trajectory_ate(identity_poses(seq.c2w), seq.c2w)),
            SequenceScores(seq.name, "const-velocity", trajectory_ate(constant_velocity_poses(seq.c2w), seq.c2w))]


class _ReplayedModel:
    """Hands a second tracker the outputs the first tracker's identical calls produced (one model pass for both).

    Both trackers cut submaps at the same frames, so they call `init_state` and `step` in the same order with the
    same inputs; only what they do with the outputs (the pose source) differs.
    """

    def __init__(self, model) -> None:
        self.model = model
        self.recorded: list = []
        self.replaying = False

    def init_state(self, batch: int = 1):
        return self.model.init_state(batch)

    def step(self, image: torch.Tensor, state, update: bool = True):
        if self.replaying:
            return self.recorded.pop(0)
        out = self.model.step(image, state, update)
        self.recorded.append(out)
        return out


def evaluate_model(model, seq: EvalSequence, method: str = "model", submap_length: int = 8) -> SequenceScores:
    """Track the sequence with the model (submaps, no backend) and score poses (both pose sources), depth and raw
    surfels (own view and next view)."""
    from worker.frontend.tracker import SubmapTracker, TrackerConfig
    from worker.geometry import Intrinsics

    model.eval()
    shared = _ReplayedModel(model)
    trackers = {source: SubmapTracker(shared, TrackerConfig(submap_length=submap_length, pose_source=source))
                for source in ("head", "pointmap")}
    H, W = seq.images.shape[1:3]
    intr = Intrinsics.from_matrix(torch.as_tensor(seq.K), W, H)
    poses: dict[str, list] = {source: [] for source in trackers}
    rels, psnrs, psnrs_next = [], [], []
    for i, image in enumerate(seq.images):
        chw = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
        for n, (source, tracker) in enumerate(trackers.items()):
            shared.replaying = n > 0
            tracked = tracker.track(i, chw, intr)
            poses[source].append(tracked.pose_world.numpy())
        if shared.recorded:
            raise RuntimeError("the trackers' model calls diverged")
        rels.append(depth_abs_rel(tracked.surfels.points[..., 2].float().numpy(), seq.depths[i]))
        psnrs.append(raw_surfel_psnr(tracked.surfels, image, seq.K))
        if i + 1 < len(seq.images):
            cam_to_next = np.linalg.inv(seq.c2w[i + 1]) @ seq.c2w[i]
            psnrs_next.append(next_view_psnr(tracked.surfels, seq.depths[i], cam_to_next, seq.images[i + 1], seq.K))

    def mean(values: list[float]) -> float:
        finite = [v for v in values if math.isfinite(v)]
        return float(np.mean(finite)) if finite else math.nan

    return SequenceScores(seq.name, method, trajectory_ate(np.stack(poses["head"]), seq.c2w), mean(rels),
                          mean(psnrs), mean(psnrs_next), trajectory_ate(np.stack(poses["pointmap"]), seq.c2w))
