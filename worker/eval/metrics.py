"""The paper's metrics.

- ATE RMSE: RMSE of camera-centre errors after aligning the estimate to the reference with Umeyama over positions:
  Sim(3) (`align="sim3"`, monocular; equals `evo_ape tum ref est -as`), SE(3) (`"se3"`, `-a`) or none.
- PSNR: images in [0, 1] (float inputs clamped, uint8 divided by 255), MSE over all pixels and channels.
- SSIM: 11x11 Gaussian window (sigma 1.5), C1 = 1e-4, C2 = 9e-4, per channel, zero padding (same-size map, as the
  3DGS/2DGS/MonoGS code), mean of the map.
- LPIPS (AlexNet, v0.1): only when the backbone and the linear heads are on disk (see `worker.eval.lpips`).
- Depth L1: mean |s * D_pred - D_gt| in metres over pixels where both are valid; s = 1 for RGB-D/metric runs,
  s = median(D_gt) / median(D_pred) per frame for monocular runs (or a least-squares scale).
- FPS: end to end, total frames / total runtime (paper appendix E).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
import torch

from worker.data.tum_trajectory import Trajectory, associate_trajectories
from worker.geometry import umeyama

from .images import as_image_batch

ALIGNMENTS = ("sim3", "se3", "none")
DEPTH_SCALINGS = ("median", "lstsq", "none")


# ---- trajectories --------------------------------------------------------------------------------------------------
@dataclass
class AteResult:
    """Absolute trajectory error statistics (metres, in the reference's units) after alignment.

    alignment: the 4x4 similarity applied to the estimate; scale: its scale; errors: per-pose errors [N].
    """

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    scale: float
    num_poses: int
    alignment: np.ndarray
    errors: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["alignment"] = self.alignment.tolist()
        d.pop("errors")
        return d


def _positions(poses: Trajectory | np.ndarray) -> np.ndarray:
    if isinstance(poses, Trajectory):
        return poses.positions
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim == 3 and array.shape[1:] == (4, 4):
        return array[:, :3, 3]
    if array.ndim == 2 and array.shape[1] == 3:
        return array
    raise ValueError(f"expected a Trajectory, poses [N, 4, 4] or positions [N, 3], got shape {array.shape}")


def alignment_transform(estimate: np.ndarray, reference: np.ndarray, align: str = "sim3") -> np.ndarray:
    """The 4x4 transform (Sim(3), SE(3) or identity) that best maps estimate positions [N, 3] onto reference [N, 3]."""
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    if align == "none":
        return np.eye(4)
    if len(estimate) < 3:
        raise ValueError(f"alignment needs at least 3 poses, got {len(estimate)}")
    s, R, t = umeyama(torch.from_numpy(estimate), torch.from_numpy(reference), with_scale=align == "sim3")
    T = np.eye(4)
    T[:3, :3] = float(s) * R.numpy()
    T[:3, 3] = t.numpy()
    return T


def absolute_trajectory_error(
    estimate: Trajectory | np.ndarray,
    reference: Trajectory | np.ndarray,
    align: str = "sim3",
    max_difference: float = 0.01,
) -> AteResult:
    """ATE of an estimate against a reference.

    Two Trajectory objects are associated by timestamp first (within max_difference seconds); arrays ([N, 4, 4]
    poses or [N, 3] positions) are taken as already paired.
    """
    if isinstance(estimate, Trajectory) and isinstance(reference, Trajectory):
        estimate, reference = associate_trajectories(estimate, reference, max_difference)
    est, ref = _positions(estimate), _positions(reference)
    if est.shape != ref.shape:
        raise ValueError(f"estimate and reference must pair up, got {est.shape} and {ref.shape}")
    if len(est) == 0:
        raise ValueError("no poses to evaluate")
    T = alignment_transform(est, ref, align)
    aligned = est @ T[:3, :3].T + T[:3, 3]
    errors = np.linalg.norm(aligned - ref, axis=1)
    return AteResult(
        rmse=float(np.sqrt(np.mean(errors ** 2))), mean=float(errors.mean()), median=float(np.median(errors)),
        std=float(errors.std()), min=float(errors.min()), max=float(errors.max()),
        scale=float(np.cbrt(np.linalg.det(T[:3, :3]))), num_poses=len(errors), alignment=T, errors=errors,
    )


def ate_rmse(estimate, reference, align: str = "sim3", max_difference: float = 0.01) -> float:
    """Just the RMSE of `absolute_trajectory_error`."""
    return absolute_trajectory_error(estimate, reference, align, max_difference).rmse


# ---- images --------------------------------------------------------------------------------------------------------
def _pair(prediction, target) -> tuple[torch.Tensor, torch.Tensor]:
    pred, gt = as_image_batch(prediction), as_image_batch(target)
    if pred.shape != gt.shape:
        raise ValueError(f"images differ in shape: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    return pred, gt


def psnr(prediction, target, mask: np.ndarray | torch.Tensor | None = None) -> float:
    """PSNR in dB of one image (or the mean over a batch) against its target; mask [H, W] limits the pixels.

    Identical images give +inf.
    """
    pred, gt = _pair(prediction, target)
    sq = (pred - gt) ** 2
    if mask is None:
        mse = sq.mean(dim=(1, 2, 3))
    else:
        m = torch.as_tensor(np.asarray(mask) if not isinstance(mask, torch.Tensor) else mask).bool()
        if m.shape != pred.shape[-2:]:
            raise ValueError(f"mask must be [H, W] = {tuple(pred.shape[-2:])}, got {tuple(m.shape)}")
        if not m.any():
            raise ValueError("mask selects no pixels")
        mse = sq[:, :, m].mean(dim=(1, 2))
    values = [math.inf if v == 0 else -10.0 * math.log10(v) for v in mse.tolist()]
    return float(np.mean(values))


def gaussian_kernel_1d(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Normalised 1D Gaussian [size]; the 2D SSIM window is its outer product."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def ssim_map(prediction, target, window: int = 11, sigma: float = 1.5, c1: float = 1e-4, c2: float = 9e-4):
    """The per-pixel, per-channel SSIM map [B, 3, H, W] (zero-padded Gaussian window, applied separably)."""
    pred, gt = _pair(prediction, target)
    g = gaussian_kernel_1d(window, sigma).numpy()

    def blur(x: np.ndarray) -> np.ndarray:  # [H, W, 3] float64; zero padding like the 3DGS conv2d
        return cv2.sepFilter2D(x, cv2.CV_64F, g, g, borderType=cv2.BORDER_CONSTANT)

    maps = []
    for x, y in zip(pred.permute(0, 2, 3, 1).numpy(), gt.permute(0, 2, 3, 1).numpy()):
        x, y = np.ascontiguousarray(x), np.ascontiguousarray(y)
        mu_x, mu_y = blur(x), blur(y)
        var_x, var_y, cov = blur(x * x) - mu_x ** 2, blur(y * y) - mu_y ** 2, blur(x * y) - mu_x * mu_y
        maps.append(((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2)))
    return torch.from_numpy(np.stack(maps)).permute(0, 3, 1, 2)


def ssim(prediction, target) -> float:
    """Mean SSIM (11x11 Gaussian, sigma 1.5, C1 = 1e-4, C2 = 9e-4) of one image or a batch."""
    return float(ssim_map(prediction, target).mean())


# ---- depth ---------------------------------------------------------------------------------------------------------
@dataclass
class DepthL1:
    """Mean absolute depth error in metres after scaling the prediction by `scale` (mode: median|lstsq|none)."""

    value: float
    scale: float
    mode: str
    valid_pixels: int


def depth_l1(prediction, target, scaling: str = "median", max_depth: float | None = None) -> DepthL1:
    """Depth L1 of a predicted/rendered depth [H, W] against ground truth [H, W] (metres, 0 = invalid).

    scaling: "median" (monocular: s = median(gt) / median(pred) over valid pixels), "lstsq" (s minimising
    sum (s p - g)^2) or "none" (metric, RGB-D). Pixels count where both depths are finite and > 0 (and gt <=
    max_depth when given).
    """
    if scaling not in DEPTH_SCALINGS:
        raise ValueError(f"scaling must be one of {DEPTH_SCALINGS}, got {scaling!r}")
    pred = np.asarray(prediction.detach().cpu() if isinstance(prediction, torch.Tensor) else prediction, np.float64)
    gt = np.asarray(target.detach().cpu() if isinstance(target, torch.Tensor) else target, np.float64)
    pred, gt = np.squeeze(pred), np.squeeze(gt)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise ValueError(f"depth maps must both be [H, W], got {pred.shape} and {gt.shape}")
    valid = np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    if max_depth is not None:
        valid &= gt <= max_depth
    if not valid.any():
        raise ValueError("no pixel has both a valid predicted and a valid ground-truth depth")
    p, g = pred[valid], gt[valid]
    if scaling == "median":
        scale = float(np.median(g) / np.median(p))
    elif scaling == "lstsq":
        scale = float((p * g).sum() / (p * p).sum())
    else:
        scale = 1.0
    return DepthL1(float(np.abs(scale * p - g).mean()), scale, scaling, int(valid.sum()))


# ---- speed and size ------------------------------------------------------------------------------------------------
def end_to_end_fps(total_frames: int, total_runtime_s: float) -> float:
    """Paper appendix E: total frames / total runtime (everything included: frontend, backend, loops, PGO)."""
    if total_frames < 0 or total_runtime_s <= 0:
        raise ValueError(f"need frames >= 0 and a positive runtime, got {total_frames} frames in {total_runtime_s} s")
    return total_frames / total_runtime_s


def gaussian_count(surfels) -> int:
    """Number of primitives in a map (a Surfels, anything with `means` [N, 3], or an int)."""
    if isinstance(surfels, int):
        return surfels
    means = getattr(surfels, "means", None)
    if means is None:
        raise ValueError(f"cannot count Gaussians of a {type(surfels).__name__}")
    return int(means.shape[0])


# ---- rendering evaluation on non-keyframes -------------------------------------------------------------------------
def non_keyframe_indices(is_keyframe: Sequence[bool], every: int = 1) -> list[int]:
    """Indices of frames that are not keyframes, then every `every`-th of them (MonoGS evaluates every 5th)."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    return [i for i, key in enumerate(is_keyframe) if not key][::every]


@dataclass
class RenderingScores:
    """Mean image metrics over the evaluated frames (lpips None when unavailable, with lpips_note saying why)."""

    psnr: float
    ssim: float
    lpips: float | None
    depth_l1: float | None  # None when no frame had rendered and ground-truth depth in common
    num_frames: int
    lpips_note: str = ""
    psnr_per_frame: tuple[float, ...] = ()  # in the order of the frames evaluated


def hole_shares(alpha: np.ndarray, threshold: float = 0.5) -> tuple[float, float]:
    """(share of the image the map leaves uncovered, share of its largest connected uncovered region): pixels whose
    accumulated opacity is below `threshold` are holes."""
    hole = (np.asarray(alpha) < threshold).astype(np.uint8)
    if not hole.any():
        return 0.0, 0.0
    _, _, stats, _ = cv2.connectedComponentsWithStats(hole, connectivity=4)
    return float(hole.mean()), float(stats[1:, cv2.CC_STAT_AREA].max() / hole.size)


def evaluate_renders(
    render: Callable[[np.ndarray, object], tuple[np.ndarray, np.ndarray | None]],
    frames: Iterable,
    poses: Sequence[np.ndarray],
    depth_scaling: str = "median",
    lpips_metric=None,
) -> RenderingScores:
    """Render each frame from its estimated pose and score it against the frame's image (and depth when both exist).

    render(pose_c2w, intrinsics) -> (rgb [H, W, 3], depth [H, W] or None); frames: the Frames to evaluate (pick
    non-keyframes with `non_keyframe_indices`), poses: their estimated poses in the map's frame, in order.
    lpips_metric: an `Lpips` instance or None (then `Lpips.load()` is tried once).
    """
    from .lpips import Lpips

    if lpips_metric is None:
        lpips_metric = Lpips.load()
    psnrs, ssims, lpipss, depths = [], [], [], []
    count = 0
    for frame, pose in zip(frames, poses, strict=True):
        rgb, depth = render(np.asarray(pose), frame.intrinsics)
        psnrs.append(psnr(rgb, frame.image))
        ssims.append(ssim(rgb, frame.image))
        if lpips_metric.available:
            lpipss.append(lpips_metric(rgb, frame.image))
        if depth is not None and frame.depth is not None:
            try:
                depths.append(depth_l1(depth, frame.depth, depth_scaling).value)
            except ValueError:  # the map draws nothing with depth here: no depth error to score
                pass
        count += 1
    if count == 0:
        raise ValueError("no frames to evaluate")
    return RenderingScores(
        psnr=float(np.mean(psnrs)), ssim=float(np.mean(ssims)),
        lpips=float(np.mean(lpipss)) if lpipss else None,
        depth_l1=float(np.mean(depths)) if depths else None, num_frames=count,
        lpips_note="" if lpips_metric.available else lpips_metric.reason, psnr_per_frame=tuple(map(float, psnrs)),
    )
