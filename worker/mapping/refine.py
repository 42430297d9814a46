"""Lightweight local map refinement (paper sec. 4.3): a few Adam steps on the surfels of the last K keyframes.

Parameters are optimised in raw (pre-activation) form: means, log scales, logit opacities, unnormalised quaternions
and colours (clamped to [0,1] after each step). Surfels outside the window are rendered as fixed context. Each
iteration renders one keyframe of the window (newest first, then round robin) and minimises
(1 - lambda) L1 + lambda (1 - SSIM) + lambda_depth * depth L1 (when that keyframe has a reference depth; normalised
by the median reference depth). With `RefineSettings.exposure`, the loss compares each view's render under its
exposure (see worker.mapping.exposure; estimated by the map, in closed form, never here) to the photo: the map
learns exposure-normalised colours. The exposures stay fixed while the colours train: a view's exposure and the
colours of the surfels only it sees explain its photo alike, so re-fitting one against the other lets both drift.

Cost: only the surfels that some window view can draw (the rasterizer's own culling rule) take part, so the
rendered images and the gradients are those of the whole map while the rest of the map costs nothing per
iteration; SSIM is computed on 2x2 block averages by default (`ssim_downsample`), L1 and depth at full resolution.
The loop's small torch operators run on one thread and the compiled rasterizer on torch's thread count: measured on
the shared 2-core machine, torch's OpenMP workers (spinning, then slow to wake under load) made every small operator
cost milliseconds and the 20 iterations 3x slower.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from . import raster_cpu
from .background import composite
from .exposure import apply_exposure
from .losses import depth_l1, photometric_loss
from .rasterize import rasterize, visible_mask
from .surfels import Surfels
from .view_poses import ViewPoseCorrections

_OPACITY_EPS = 1e-4


@dataclass(frozen=True)
class RefineSettings:
    """Optimiser settings; position learning rate is relative to the scene's median depth (monocular scale)."""

    lambda_ssim: float = 0.2
    lambda_depth: float = 0.1
    lr_means: float = 1e-3
    lr_log_scales: float = 5e-3
    lr_opacity_logits: float = 0.05
    lr_quats: float = 1e-3
    lr_colors: float = 0.01
    ssim_downsample: int = 2  # SSIM on factor x factor block averages (factor^2 cheaper); 1 = full resolution
    exposure: bool = False  # per-keyframe affine exposure (applied to views whose `exposure` is not None)
    exposure_prior: float = 0.002  # estimates: weight of the identity gain against the fitted one
    exposure_min_alpha: float = 0.95  # estimates: pixels the render covers at least this much take part
    exposure_threshold: float = 0.03  # estimates: log-gain changes within this are shrunk away (shrink_exposure)
    exposure_shared: bool = True  # estimates: one gain for the three channels (fit_exposure's `shared`)
    lr_pose_translation: float = 2e-4  # trainable cameras: a view's camera shift per step, times the scene scale
    lr_pose_rotation: float = 2e-4  # ... and its turn per step, radians


@dataclass
class RefineView:
    """One keyframe as seen by the refinement: rigid world-to-camera matrix, K, target image and optional depth.

    `depth_scale` converts rendered depth (world units) to the reference depth's units (reference = render / scale).
    `exposure`: the keyframe's affine exposure [6] (worker.mapping.exposure), applied to its renders when the
    settings ask for it; None = the identity.
    """

    viewmat: torch.Tensor
    K: torch.Tensor
    image: torch.Tensor  # [H, W, 3] float in [0, 1]
    depth: torch.Tensor | None = None
    depth_scale: float = 1.0
    exposure: torch.Tensor | None = None
    background: torch.Tensor | None = None  # [H, W, 3]: what the view sees behind the surfels (map's background)


@dataclass
class RefineReport:
    """Losses per iteration and the index (into the views) each iteration rendered."""

    losses: list[float] = field(default_factory=list)
    views: list[int] = field(default_factory=list)
    # with trainable_cameras: every view's camera-frame correction (float64 4x4; viewmat -> correction @ viewmat)
    view_corrections: list[torch.Tensor] = field(default_factory=list)


class _RawParams(torch.nn.Module):
    def __init__(self, surfels: Surfels):
        super().__init__()
        s = surfels.detach()
        self.means = torch.nn.Parameter(s.means.clone())
        self.log_scales = torch.nn.Parameter(torch.log(s.scales.clamp_min(1e-12)))
        self.opacity_logits = torch.nn.Parameter(torch.logit(s.opacities.clamp(_OPACITY_EPS, 1 - _OPACITY_EPS)))
        self.quats = torch.nn.Parameter(s.quats.clone())
        self.colors = torch.nn.Parameter(s.colors.clone())
        self.keyframe_ids = s.keyframe_ids

    def surfels(self) -> Surfels:
        return Surfels(self.means, self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12),
                       torch.exp(self.log_scales), torch.sigmoid(self.opacity_logits), self.colors, self.keyframe_ids)


def refine_surfels(
    surfels: Surfels,
    trainable: torch.Tensor,
    views: list[RefineView],
    iterations: int = 20,
    settings: RefineSettings | None = None,
    scene_scale: float = 1.0,
    deadline: float | None = None,
    lr_schedule: Callable[[int], float] | None = None,
    after_step: Callable[[], None] | None = None,
    trainable_cameras: list[bool] | None = None,
) -> tuple[Surfels, RefineReport]:
    """Optimise the surfels selected by `trainable` ([N] bool) against `views` (newest last) for `iterations` steps,
    fewer when `time.perf_counter()` passes `deadline` (checked before each step). With `lr_schedule`, step `it`
    runs at the settings' learning rates times `lr_schedule(it)` (a decay, for a pass whose result should not
    depend on the last views it saw). `after_step` is called after each step (the mapping stage lets readers of
    the map in there: `surfels` itself is not changed until the end). With `trainable_cameras` (a flag per view), the
    flagged views' cameras are refined with the surfels (worker.mapping.view_poses) and the report holds every
    view's correction; at least one camera should stay fixed, or the map and all cameras drift together (gauge).

    Returns the updated map (same order and size as `surfels`) and a report of the losses.
    """
    settings = settings or RefineSettings()
    if trainable.shape != (len(surfels),) or trainable.dtype != torch.bool:
        raise ValueError("trainable must be a [N] bool mask over the surfels")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    report = RefineReport()
    if iterations == 0 or not views or not bool(trainable.any()):
        return surfels, report

    in_view = _drawn_by_any_view(surfels, views)
    optimised = trainable & in_view
    if not bool(optimised.any()):
        return surfels, report
    params = _RawParams(surfels.select(optimised))
    fixed = surfels.select(~trainable & in_view).detach()
    groups = [
        {"params": [params.means], "lr": settings.lr_means * scene_scale},
        {"params": [params.log_scales], "lr": settings.lr_log_scales},
        {"params": [params.opacity_logits], "lr": settings.lr_opacity_logits},
        {"params": [params.quats], "lr": settings.lr_quats},
        {"params": [params.colors], "lr": settings.lr_colors},
    ]
    cameras = None
    if trainable_cameras is not None:
        if len(trainable_cameras) != len(views):
            raise ValueError("trainable_cameras needs one flag per view")
        cameras = ViewPoseCorrections(len(views), views[0].viewmat.dtype, views[0].viewmat.device)
        moving = [i for i, flag in enumerate(trainable_cameras) if flag]
        for i, flag in enumerate(trainable_cameras):
            cameras.translations[i].requires_grad_(flag)
            cameras.rotations[i].requires_grad_(flag)
        groups += [{"params": [cameras.translations[i] for i in moving],
                    "lr": settings.lr_pose_translation * scene_scale},
                   {"params": [cameras.rotations[i] for i in moving], "lr": settings.lr_pose_rotation}]
    optimizer = torch.optim.Adam(groups, eps=1e-15)
    depth_scales = [_median_depth(v.depth) for v in views]
    order = list(range(len(views) - 1, -1, -1))  # newest first
    with _serial_torch_parallel_kernels():
        _optimise(params, fixed, views, depth_scales, order, optimizer, iterations, settings, report, deadline,
                  lr_schedule, after_step, cameras)
    if cameras is not None:
        report.view_corrections = cameras.corrections()

    out = surfels.detach().clone()
    refined = params.surfels().detach()
    for name, value in refined.tensors().items():
        getattr(out, name)[optimised] = value
    return out, report


def _drawn_by_any_view(surfels: Surfels, views: list[RefineView]) -> torch.Tensor:
    """[N] bool: surfels that at least one view's render can touch."""
    mask = torch.zeros(len(surfels), dtype=torch.bool, device=surfels.device)
    for view in views:
        H, W = view.image.shape[:2]
        mask |= visible_mask(surfels, view.viewmat, view.K, W, H)
    return mask


def _median_depth(depth: torch.Tensor | None) -> torch.Tensor | None:
    """Median of the valid (> 0) reference depth, the depth term's normaliser; None without valid depth."""
    if depth is None or not bool((depth > 0).any()):
        return None
    return depth[depth > 0].median().clamp_min(1e-6)


def _optimise(params: _RawParams, fixed: Surfels, views: list[RefineView], depth_scales: list, order: list[int],
              optimizer: torch.optim.Optimizer, iterations: int, settings: RefineSettings,
              report: RefineReport, deadline: float | None = None,
              lr_schedule: Callable[[int], float] | None = None,
              after_step: Callable[[], None] | None = None,
              cameras: ViewPoseCorrections | None = None) -> None:
    """The Adam iterations (each renders one view of the window, round robin over `order`), until `deadline`;
    with `cameras`, each view is rendered from its corrected camera."""
    base_lrs = [group["lr"] for group in optimizer.param_groups]
    for it in range(iterations):
        if deadline is not None and time.perf_counter() >= deadline:
            break
        if lr_schedule is not None:
            factor = float(lr_schedule(it))
            if not factor > 0:
                raise ValueError(f"a learning-rate factor must be positive, got {factor} at step {it}")
            for group, base in zip(optimizer.param_groups, base_lrs):
                group["lr"] = base * factor
        index = order[it % len(order)]
        view = views[index]
        H, W = view.image.shape[:2]
        current = Surfels.concat([params.surfels(), fixed]) if len(fixed) else params.surfels()
        viewmat = view.viewmat if cameras is None else cameras.viewmat(index, view.viewmat)
        render = rasterize(current, viewmat, view.K, W, H)
        rgb = composite(render.rgb, render.alpha, view.background)
        if settings.exposure and view.exposure is not None:
            rgb = apply_exposure(rgb, view.exposure)
        loss = photometric_loss(rgb, view.image, settings.lambda_ssim, settings.ssim_downsample)
        if view.depth is not None and settings.lambda_depth > 0 and depth_scales[index] is not None:
            covered = render.alpha.detach() > 0.5
            loss = loss + settings.lambda_depth * depth_l1(render.depth / view.depth_scale, view.depth, covered,
                                                           depth_scales[index])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        with torch.no_grad():
            params.colors.clamp_(0.0, 1.0)
        report.losses.append(float(loss.detach()))
        report.views.append(index)
        if after_step is not None:
            after_step()


@contextlib.contextmanager
def _serial_torch_parallel_kernels():
    """Torch operators on one thread (this calling thread), the compiled rasterizer on torch's thread count."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        with raster_cpu.using_threads(threads):
            yield
    finally:
        torch.set_num_threads(threads)
