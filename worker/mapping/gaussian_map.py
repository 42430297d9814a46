"""The backend's global 2DGS map (paper sec. 4.3): fuse keyframes, refine the recent window, follow loop closures.

Keyframe poses are camera-to-world Sim(3) matrices [sR|t]. Renders use the rigid part [R|t] (world->camera
viewmat = its inverse), so rendered depth is in world units; a keyframe's own camera-frame depth equals the
world-unit depth divided by its scale s.

With `refine.exposure`, each keyframe has an affine exposure (worker.mapping.exposure), always estimated in closed
form against the render of the *rest* of the map (never against its own surfels, whose colours and its exposure
explain its photo alike): when the keyframe is added (its new surfels get exposure-normalised colours), again
before a catch-up refinement of it and before the final global refinement (`estimate_exposure`), where the map
around it has been refined; refinements apply the exposures as they are. The first keyframe's stays the identity
(the gauge: the map's colour scale), and estimates are shrunk toward the identity (`refine.exposure_threshold`).
Renders use the normalised colours.
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
import torch

from worker.geometry import make_sim3, sim3_decompose, sim3_inverse

from .archive_thinning import thin
from .background import DirectionalBackground, composite
from .exposure import apply_exposure, fit_exposure, identity_exposure, interpolate_exposure, remove_exposure
from .fusion import FusionThresholds, attribute_errors, densify_mask, prune_mask
from .hole_closing import HoleClosingSettings, hole_surfels, widened_camera
from .keyframe_archive import ArchivedKeyframe
from .loop_correction import correct_map
from .ply import surfels_to_ply_bytes
from .rasterize import RenderResult, rasterize, visible_mask
from .refine import RefineReport, RefineSettings, RefineView, refine_surfels
from .surfels import Surfels
from .voxel_grid import capped_mask, voxel_keys

# A keyframe's exposure is fitted to the map's render when the map covers at least this fraction of its view.
MIN_EXPOSURE_COVERAGE = 0.05


@dataclass
class MapConfig:
    """Backend map settings (paper defaults where the paper gives them: K window, 20 iterations)."""

    window: int = 5  # K: keyframes whose surfels are refined
    iterations: int = 20  # refinement iterations per keyframe
    thresholds: FusionThresholds = field(default_factory=FusionThresholds)
    refine: RefineSettings = field(default_factory=RefineSettings)
    min_opacity: float = 0.005  # surfels fading below this after refinement are removed
    # Keyframes outside the window whose image and depth stay (compact: keyframe_archive) for refinement; when more
    # have left the window, the most redundant views are let go (archive_thinning). 0 = keep only the window's.
    archived_images: int = 0
    # Each refinement also trains against this many archived keyframes drawn at random (seeded), with their
    # surfels: the online map keeps the views the window has left (MonoGS-style random past keyframes).
    archived_views_per_refine: int = 0
    # Voxel cap (worker.mapping.voxel_grid): a keyframe adds surfels to a world voxel only when it offers more than
    # `voxel_finer` times the surfels the map has there (a closer view), up to `voxel_cap`, so revisits do not grow
    # the map. Voxel side: `voxel_pixels` pixels of the first keyframe at its median depth (world units; monocular
    # maps have arbitrary scale). voxel_cap 0 = no cap.
    voxel_cap: int = 64
    voxel_pixels: float = 8.0
    voxel_finer: float = 1.5
    # refine_global stops after this many seconds whatever its iteration count (None = no bound).
    final_refine_budget_s: float | None = 25.0
    # refine_global's learning rates fall geometrically to this factor of the settings' over its iterations
    # (1 = constant), so its result depends less on the views it happened to see last.
    final_refine_lr_end: float = 1.0
    # refine_global first closes the holes of every held keyframe's widened view (close_holes); None = it does not.
    hole_closing: HoleClosingSettings | None = None
    # Renders and refinement show, behind the surfels, the colour keyframes saw in each world direction where the map
    # left them uncovered (worker.mapping.background: the sky, surfaces without stereo depth); False = black.
    background: bool = False
    device: str = "cpu"

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> MapConfig:
        d = dict(d)
        thresholds = FusionThresholds(**d.pop("thresholds", {}))
        refine = RefineSettings(**d.pop("refine", {}))
        closing = d.pop("hole_closing", None)
        return cls(thresholds=thresholds, refine=refine,
                   hole_closing=None if closing is None else HoleClosingSettings(**closing), **d)


@dataclass
class FusionStats:
    """What `add_keyframe` did."""

    pruned: int
    added: int
    skipped: int


@dataclass
class _Keyframe:
    pose: torch.Tensor  # [4,4] float64 camera-to-world Sim(3)
    K: torch.Tensor  # [3,3] float32
    width: int
    height: int
    image: torch.Tensor | None  # [H,W,3] float32 in [0,1] while in the window; None once archived or dropped
    depth: torch.Tensor | None  # [H,W] float32 camera-frame z (0 = unknown)
    archived: ArchivedKeyframe | None = None  # image and depth, compact, once out of the window
    exposure: torch.Tensor | None = None  # [6] gain, bias (worker.mapping.exposure); None = the identity

    @property
    def held(self) -> bool:
        """Whether this keyframe can still be a refinement target."""
        return self.image is not None or self.archived is not None

    def refine_view(self, with_exposure: bool = False) -> RefineView:
        """This keyframe as a refinement target (it must be held), seen with its exposure or none (identity)."""
        if self.archived is not None:
            image, depth = self.archived.unpack(self.K.device)
        else:
            assert self.image is not None
            image, depth = self.image, self.depth
        viewmat, scale = rigid_viewmat(self.pose)
        own = None
        if with_exposure:
            own = identity_exposure(self.K.device) if self.exposure is None else self.exposure
        return RefineView(viewmat.to(self.K.device, torch.float32), self.K, image, depth, scale, own)

    def archive(self) -> None:
        """Compact storage once out of the refinement window (see worker.mapping.keyframe_archive)."""
        if self.image is not None:
            self.archived = ArchivedKeyframe.pack(self.image, self.depth)
        self.image = self.depth = None

    def drop(self) -> None:
        self.image = self.depth = self.archived = None


def rigid_viewmat(pose_c2w: torch.Tensor) -> tuple[torch.Tensor, float]:
    """(world->camera rigid 4x4 of a camera-to-world Sim(3), its scale s)."""
    s, R, t = sim3_decompose(pose_c2w.to(torch.float64))
    return sim3_inverse(make_sim3(R, t)), float(s)


def corrected_pose(pose_c2w: torch.Tensor, correction: torch.Tensor) -> torch.Tensor:
    """The camera-to-world Sim(3) whose rigid viewmat is `correction` @ the viewmat of `pose_c2w` (its scale kept)."""
    s, R, t = sim3_decompose(pose_c2w.to(torch.float64))
    rigid = make_sim3(R, t) @ torch.linalg.inv(correction.to(torch.float64))
    return make_sim3(rigid[:3, :3], rigid[:3, 3], s)


def _as_K(K) -> torch.Tensor:
    """3x3 float32 intrinsics from a tensor, an array or an `Intrinsics`."""
    if hasattr(K, "matrix"):
        K = K.matrix()
    K = torch.as_tensor(np.asarray(K) if not torch.is_tensor(K) else K, dtype=torch.float32).cpu()
    if tuple(K.shape) != (3, 3):
        raise ValueError(f"K must be 3x3, got {tuple(K.shape)}")
    return K


def _as_pose(pose: torch.Tensor | np.ndarray, what: str) -> torch.Tensor:
    pose = torch.as_tensor(np.asarray(pose) if not torch.is_tensor(pose) else pose).to(torch.float64).cpu()
    if tuple(pose.shape) != (4, 4) or not torch.isfinite(pose).all():
        raise ValueError(f"{what} must be a finite 4x4 matrix, got shape {tuple(pose.shape)}")
    s = torch.linalg.det(pose[:3, :3])
    if s <= 0:
        raise ValueError(f"{what} must be a proper Sim(3) (positive determinant)")
    return pose


class GaussianMap:
    """The global surfel map the SLAM backend drives.

    add_keyframe: prune by render error -> transform to world (eq. 17) -> add where accumulation < tau_accum.
    refine: Adam on the surfels of the last `window` keyframes. apply_pose_updates: rigid per-keyframe correction.
    """

    def __init__(self, config: MapConfig | None = None):
        self.config = config or MapConfig()
        self.device = torch.device(self.config.device)
        self._surfels = Surfels.empty(self.device)
        self._keyframes: dict[int, _Keyframe] = {}
        self._voxel_size: float | None = None  # world units, fixed by the first keyframe (see MapConfig.voxel_size)
        self._background = DirectionalBackground() if self.config.background else None

    # -- read access -------------------------------------------------------------------------------------------
    @property
    def surfels(self) -> Surfels:
        return self._surfels

    @property
    def num_gaussians(self) -> int:
        return len(self._surfels)

    @property
    def keyframe_ids(self) -> list[int]:
        """Keyframe ids in insertion order."""
        return list(self._keyframes)

    def keyframe_pose(self, kf_id: int) -> torch.Tensor:
        return self._keyframes[kf_id].pose.clone()

    # -- updates -----------------------------------------------------------------------------------------------
    @property
    def keeps_background(self) -> bool:
        """Whether renders and refinement composite the map's background behind the surfels."""
        return self._background is not None

    def keep_background(self) -> None:
        """Keep a background behind the map from now on (worker.mapping.background), as `MapConfig.background`
        does from the start; keyframes already fused add nothing to it."""
        if self._background is None:
            self._background = DirectionalBackground()

    def add_keyframe(self, kf_id: int, pose_c2w: torch.Tensor, K: torch.Tensor, image: torch.Tensor,
                     surfels_cam: Surfels, depth: torch.Tensor | None = None) -> FusionStats:
        """Fuse a keyframe's camera-frame surfels into the map.

        image: [H,W,3] float in [0,1] (uint8 is converted); depth: optional [H,W] camera-frame z used for pruning
        and as the refinement's depth target (0 = unknown).
        """
        kf_id = int(kf_id)
        if kf_id in self._keyframes:
            raise ValueError(f"keyframe {kf_id} is already in the map")
        pose = _as_pose(pose_c2w, "pose_c2w")
        kf = self._make_keyframe(pose, K, image, depth)
        if not isinstance(surfels_cam, Surfels):
            raise ValueError("surfels_cam must be a Surfels")
        surfels_cam = surfels_cam.detach().to(self.device, torch.float32)
        viewmat, scale = rigid_viewmat(pose)
        viewmat = viewmat.to(self.device, torch.float32)
        th = self.config.thresholds

        pruned = 0
        accumulation = torch.zeros(kf.height, kf.width, device=self.device)
        # Only the surfels this view can draw take part (the rasterizer's own culling rule, so the render is the
        # whole map's): the merge costs what the view holds, not what the map holds.
        in_view = self._in_view(viewmat, kf.K, kf.width, kf.height)
        local = self._surfels.select(in_view)
        attribution = attribute_errors(local, viewmat, kf.K, kf.image, kf.depth, th, scale) if len(local) else None
        if self.config.refine.exposure and self._keyframes:
            previous = self._keyframes[self.keyframe_ids[-1]].exposure  # exposure changes slowly
            fitted = None if attribution is None else self._fit_exposure(attribution.render, kf.image)
            kf.exposure = fitted if fitted is not None else (
                identity_exposure(self.device) if previous is None else previous.clone())
            if not torch.equal(kf.exposure, identity_exposure(self.device)):  # prune on normalised colours
                normalised = remove_exposure(kf.image, kf.exposure).clamp(0, 1)
                surfels_cam.colors = remove_exposure(surfels_cam.colors, kf.exposure).clamp(0, 1)
                if attribution is not None:
                    attribution = attribute_errors(local, viewmat, kf.K, normalised, kf.depth, th, scale)
        if attribution is not None:
            remove = prune_mask(attribution, th)
            pruned = int(remove.sum())
            accumulation = attribution.render.alpha
            if pruned:
                drop = torch.zeros(len(self._surfels), dtype=torch.bool, device=self.device)
                drop[torch.nonzero(in_view, as_tuple=True)[0][remove]] = True
                self._surfels = self._surfels.select(~drop)
                local = local.select(~remove)
                with torch.no_grad():
                    accumulation = rasterize(local, viewmat, kf.K, kf.width, kf.height).alpha

        add = densify_mask(surfels_cam, kf.K, accumulation, th.tau_accum)
        offered = surfels_cam.transform(pose.to(self.device, torch.float32))
        if self.config.voxel_cap > 0 and len(offered):
            if self._voxel_size is None:
                median_z = float(surfels_cam.means[:, 2].median())
                self._voxel_size = self.config.voxel_pixels * scale * median_z / float(kf.K[0, 0])
            add = capped_mask(voxel_keys(local.means, self._voxel_size), voxel_keys(offered.means, self._voxel_size),
                              add, self.config.voxel_cap, self.config.voxel_finer)
        new = offered.select(add)
        new.keyframe_ids = torch.full((len(new),), kf_id, dtype=torch.int64, device=self.device)
        self._surfels = Surfels.concat([self._surfels, new])
        if self._background is not None:
            with torch.no_grad():
                alpha = rasterize(Surfels.concat([local, new]), viewmat, kf.K, kf.width, kf.height).alpha
            colours = kf.image if kf.exposure is None else remove_exposure(kf.image, kf.exposure).clamp(0, 1)
            self._background.observe(pose, kf.K, colours, alpha)
        self._keyframes[kf_id] = kf
        self._archive_old_images()
        return FusionStats(pruned=pruned, added=len(new), skipped=len(surfels_cam) - len(new))

    def keyframe_exposure(self, kf_id: int) -> torch.Tensor:
        """[6] affine exposure (gain, bias per channel) of a keyframe (the identity unless estimated)."""
        exposure = self._keyframes[int(kf_id)].exposure
        return identity_exposure(self.device) if exposure is None else exposure.clone()

    def exposure_at(self, frame_index: int) -> torch.Tensor:
        """[6] the exposure the camera had at frame `frame_index` as far as the map knows (keyframe ids are frame
        indices): a keyframe's own, else interpolated between the nearest keyframes before and after it (the
        nearest one's beyond the ends); the identity without keyframes."""
        ids = sorted(self._keyframes)
        if not ids:
            return identity_exposure(self.device)
        position = bisect.bisect_left(ids, frame_index)
        if position < len(ids) and ids[position] == frame_index:
            return self.keyframe_exposure(frame_index)
        if position == 0 or position == len(ids):
            return self.keyframe_exposure(ids[min(position, len(ids) - 1)])
        before, after = ids[position - 1], ids[position]
        return interpolate_exposure(self.keyframe_exposure(before), self.keyframe_exposure(after),
                                    (frame_index - before) / (after - before))

    def estimate_exposure(self, kf_id: int) -> bool:
        """Re-estimate a held keyframe's exposure (with `refine.exposure`; the first keyframe's excepted) against
        the render of the map without its own surfels, and re-normalise its surfels' colours to the new exposure
        (they keep explaining its photo). False when nothing changed: exposure off, the first keyframe, not held,
        or the rest of the map covers too little of its view."""
        kf = self._keyframes.get(int(kf_id))
        if not self.config.refine.exposure or kf is None or not kf.held or int(kf_id) == self.keyframe_ids[0]:
            return False
        viewmat, _ = rigid_viewmat(kf.pose)
        viewmat = viewmat.to(self.device, torch.float32)
        own = self._surfels.keyframe_ids == int(kf_id)
        others = self._surfels.select(self._in_view(viewmat, kf.K, kf.width, kf.height) & ~own)
        if len(others) == 0:
            return False
        with torch.no_grad():
            render = rasterize(others, viewmat, kf.K, kf.width, kf.height)
        image = kf.image if kf.image is not None else kf.archived.unpack(self.device)[0]
        fitted = self._fit_exposure(render, image)
        if fitted is None:
            return False
        old = identity_exposure(self.device) if kf.exposure is None else kf.exposure
        if bool(own.any()):
            colors = self._surfels.colors.clone()
            colors[own] = remove_exposure(apply_exposure(colors[own], old), fitted).clamp(0, 1)
            self._surfels.colors = colors
        kf.exposure = fitted
        return True

    def refine(self, iterations: int | None = None) -> RefineReport:
        """Refine the surfels of the last `config.window` keyframes against those keyframes' images."""
        iterations = self.config.iterations if iterations is None else int(iterations)
        window = self.keyframe_ids[-self.config.window:]
        if not window or len(self._surfels) == 0:
            return RefineReport()
        window = self._random_archived(self.config.archived_views_per_refine, exclude=window) + window
        trainable = torch.isin(self._surfels.keyframe_ids, torch.tensor(window, device=self.device))
        return self._refine(trainable, window, iterations, self._scene_scale(window))

    def refine_around(self, kf_id: int, iterations: int) -> RefineReport:
        """Refine the surfels of keyframe `kf_id` and of the `config.window - 1` held keyframes before it against
        those keyframes' images: the window `refine` had when `kf_id` was new (catching up refinement that load
        shedding skipped). Nothing when `kf_id` is not in the map or its image is no longer held."""
        ids = self.keyframe_ids
        if kf_id not in self._keyframes or not self._keyframes[kf_id].held or len(self._surfels) == 0:
            return RefineReport()
        self.estimate_exposure(kf_id)  # the map around it may have been refined since it was added
        before = [k for k in ids[:ids.index(kf_id)] if self._keyframes[k].held]
        window = before[-(self.config.window - 1):] + [kf_id] if self.config.window > 1 else [kf_id]
        trainable = torch.isin(self._surfels.keyframe_ids, torch.tensor(window, device=self.device))
        return self._refine(trainable, window, int(iterations), self._scene_scale(window))

    def _random_archived(self, count: int, exclude: list[int]) -> list[int]:
        """Up to `count` held keyframes outside `exclude`, drawn with a seed fixed by the map's keyframe count."""
        pool = [k for k in self.keyframe_ids if k not in exclude and self._keyframes[k].held]
        if count <= 0 or not pool:
            return []
        generator = torch.Generator().manual_seed(len(self._keyframes))
        return [pool[i] for i in torch.randperm(len(pool), generator=generator)[:count].sort().values.tolist()]

    def refine_global(self, iterations: int, seed: int = 0, restart_every: int | None = None,
                      budget_s: float | None = None, after_step: Callable[[], None] | None = None,
                      train_poses: bool = False) -> RefineReport:
        """Refine every surfel against every keyframe whose image is still held (the window and the archive):
        the end-of-run pass that reconciles views the window has left.

        The iterations run in chunks of `restart_every` (default: two passes over the held keyframes), each with
        a fresh optimiser and a new seeded random order of the views; the learning rates fall geometrically to
        `config.final_refine_lr_end` of the settings' over the iterations (or over the budget, where that ends the
        refinement first: `_final_lr_schedule`). Measured on ICL with constant rates (36 keyframes, 8 passes):
        a restart every 2 passes 28.9 dB, every 4 passes 28.7, every pass 28.1; one 300-iteration run 28.3.
        It stops after `budget_s` seconds (default `config.final_refine_budget_s`; math.inf: no bound) whatever
        `iterations` asks: a long session's end costs the same as a short one's. Keyframe exposures (with
        `refine.exposure`) are re-estimated first, oldest first (`estimate_exposure`: keyframes merged without
        refinement kept the fit made when they arrived), and applied as they are; then, with `config.hole_closing`,
        the holes of the keyframes' widened views are closed (`close_holes`) for the refinement to train.
        `after_step` is called after each refinement step (`refine_surfels`). With `train_poses`, the
        keyframes' cameras are refined too and their poses replaced at the end of each chunk (the surfels stay
        where the refinement put them)."""
        held = [kf_id for kf_id in self.keyframe_ids if self._keyframes[kf_id].held]
        if not held or len(self._surfels) == 0 or iterations <= 0:
            return RefineReport()
        budget = self.config.final_refine_budget_s if budget_s is None else budget_s
        deadline = None if budget is None or math.isinf(budget) else time.perf_counter() + float(budget)
        for kf_id in held:
            self.estimate_exposure(kf_id)
        if self.config.hole_closing is not None:
            self.close_holes(self.config.hole_closing, deadline)
        chunk = max(1, restart_every or 2 * len(held))
        generator = torch.Generator().manual_seed(seed)
        report = RefineReport()
        total, began = int(iterations), time.perf_counter()
        for start in range(0, total, chunk):
            if deadline is not None and time.perf_counter() >= deadline:
                break
            order = [held[i] for i in torch.randperm(len(held), generator=generator).tolist()]
            trainable = torch.ones(len(self._surfels), dtype=torch.bool, device=self.device)
            schedule = self._final_lr_schedule(start, total, began, deadline)
            part = self._refine(trainable, order, min(chunk, total - start), self._scene_scale(held), deadline,
                                schedule, after_step, train_poses)
            report.losses += part.losses
            report.views += [held.index(order[i]) for i in part.views]
        return report

    def _final_lr_schedule(self, start: int, total: int, began: float, deadline: float | None
                           ) -> Callable[[int], float] | None:
        """The final refinement's learning-rate factor at step `it` of the chunk that begins at iteration `start` of
        `total`: `final_refine_lr_end` to the power of the share of the refinement done, by iterations or, when
        a `deadline` (perf_counter) will cut it short, by time, whichever is further."""
        lr_end = self.config.final_refine_lr_end
        if lr_end == 1.0:
            return None

        def factor(it: int) -> float:
            done = (start + it) / total
            if deadline is not None and deadline > began:
                done = max(done, (time.perf_counter() - began) / (deadline - began))
            return lr_end ** min(1.0, done)

        return factor

    def close_holes(self, settings: HoleClosingSettings | None = None, deadline: float | None = None) -> int:
        """Close the holes of every held keyframe's view, widened past its border (worker.mapping.hole_closing),
        oldest first, each seeing the surfels added for the ones before; stops at `deadline` (perf_counter). The new
        surfels belong to the keyframe whose view made them. Returns how many were added."""
        settings = settings or self.config.hole_closing or HoleClosingSettings()
        added = 0
        for kf_id in [k for k in self.keyframe_ids if self._keyframes[k].held]:
            if deadline is not None and time.perf_counter() >= deadline:
                break
            kf = self._keyframes[kf_id]
            viewmat, _ = rigid_viewmat(kf.pose)
            viewmat = viewmat.to(self.device, torch.float32)
            K, width, height, offset = widened_camera(kf.K, kf.width, kf.height, settings)
            K = K.to(self.device)
            with torch.no_grad():
                render = rasterize(self._surfels.select(self._in_view(viewmat, K, width, height)), viewmat, K,
                                   width, height)
            image = kf.image if kf.image is not None else kf.archived.unpack(self.device)[0]
            if kf.exposure is not None:
                image = remove_exposure(image, kf.exposure).clamp(0, 1)
            size = (width - 2 * offset[0], height - 2 * offset[1])
            photo = cv2.resize(image.cpu().numpy(), size, interpolation=cv2.INTER_AREA)
            new = hole_surfels(render, K, photo, offset, settings)
            if len(new) == 0:
                continue
            new = new.transform(torch.linalg.inv(viewmat.double()).to(new.means.dtype))
            new.keyframe_ids = torch.full((len(new),), kf_id, dtype=torch.int64, device=self.device)
            self._surfels = Surfels.concat([self._surfels, new])
            added += len(new)
        return added

    @property
    def held_images(self) -> int:
        """Keyframes whose image is held for refinement (window + archive)."""
        return sum(kf.held for kf in self._keyframes.values())

    def keyframe_depths(self) -> dict[int, np.ndarray]:
        """Each held keyframe's target depth in world units (0 = none), by keyframe id: the depth it was mapped
        from (a sensor's, or the confident multi-view depth), for evaluation."""
        depths = {}
        for kf_id, kf in self._keyframes.items():
            if kf.held:
                view = kf.refine_view()
                if view.depth is not None:
                    depths[kf_id] = (view.depth * view.depth_scale).cpu().numpy().astype(np.float32)
        return depths

    def _refine(self, trainable: torch.Tensor, kf_ids: list[int], iterations: int, scene_scale: float,
                deadline: float | None = None, lr_schedule: Callable[[int], float] | None = None,
                after_step: Callable[[], None] | None = None, train_poses: bool = False) -> RefineReport:
        """Refine against the keyframes `kf_ids`, each seen with its exposure (with `refine.exposure`), at the
        learning rates scaled by `lr_schedule` (worker.mapping.refine.refine_surfels); with `train_poses`, their
        cameras too (all but the oldest held keyframe's, which holds the map's frame), whose corrected poses
        replace theirs."""
        views = [self._keyframes[k].refine_view(self.config.refine.exposure) for k in kf_ids]
        cameras = None
        if train_poses:
            anchor = min(k for k in self.keyframe_ids if self._keyframes[k].held)
            cameras = [k != anchor for k in kf_ids]
        if self._background is not None:
            for k, view in zip(kf_ids, views):
                kf = self._keyframes[k]
                view.background = self._background.image(kf.pose, kf.K, kf.width, kf.height, self.device)
        with torch.enable_grad():
            refined, report = refine_surfels(self._surfels, trainable, views, iterations, self.config.refine,
                                             scene_scale, deadline, lr_schedule, after_step, cameras)
        for k, correction in zip(kf_ids, report.view_corrections):
            self._keyframes[k].pose = corrected_pose(self._keyframes[k].pose, correction)
        keep = refined.opacities >= self.config.min_opacity
        self._surfels = refined.select(keep) if not bool(keep.all()) else refined
        return report

    def apply_pose_updates(self, new_poses: dict[int, torch.Tensor]) -> None:
        """Loop correction: move each keyframe's surfels by T_new T_old^-1 and store the new poses."""
        poses = {int(k): _as_pose(v, f"pose of keyframe {k}") for k, v in new_poses.items()}
        old = {k: kf.pose for k, kf in self._keyframes.items()}
        self._surfels = correct_map(self._surfels, old, poses)
        for k, pose in poses.items():
            self._keyframes[k].pose = pose

    def render(self, pose_c2w: torch.Tensor, K: torch.Tensor, width: int, height: int,
               background: torch.Tensor | None = None) -> RenderResult:
        """Render the map from a camera-to-world pose (depth in world units), over the map's background (or over
        the constant colour `background` when one is given)."""
        pose = _as_pose(pose_c2w, "pose_c2w")
        viewmat, _ = rigid_viewmat(pose)
        K = _as_K(K).to(self.device)
        with torch.no_grad():
            out = rasterize(self._surfels, viewmat.to(self.device, torch.float32), K, width, height,
                            background=None if background is None else background.to(self.device))
            if background is not None or self._background is None:
                return out
            behind = self._background.image(pose, K, width, height, self.device)
            return out._replace(rgb=composite(out.rgb, out.alpha, behind))

    def to_ply_bytes(self, variant: str = "3dgs", include_keyframe_id: bool = False) -> bytes:
        return surfels_to_ply_bytes(self._surfels, variant, include_keyframe_id)

    # -- snapshot ----------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Plain dict of numpy arrays / numbers (msgpack-able with protocol.codec.pack)."""
        keyframes = []
        for kf_id, kf in self._keyframes.items():
            keyframes.append({
                "id": kf_id, "pose": kf.pose.numpy(), "K": kf.K.cpu().numpy(), "width": kf.width,
                "height": kf.height,
                "image": None if kf.image is None else (kf.image.clamp(0, 1) * 255).round().byte().cpu().numpy(),
                "depth": None if kf.depth is None else kf.depth.cpu().numpy(),
                "archived": None if kf.archived is None else kf.archived.to_dict(),
                "exposure": None if kf.exposure is None else kf.exposure.cpu().numpy(),
            })
        return {
            "version": 1,
            "config": self.config.to_dict(),
            "surfels": {k: v.detach().cpu().numpy() for k, v in self._surfels.tensors().items()},
            "keyframes": keyframes,
            "voxel_size": self._voxel_size,
            "background": None if self._background is None else self._background.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore from `state_dict()` output (possibly round-tripped through msgpack)."""
        if not isinstance(state, dict) or state.get("version") != 1:
            raise ValueError("unsupported GaussianMap state (expected version 1)")
        try:
            surfels = Surfels(**{k: torch.from_numpy(np.array(v)).to(self.device) for k, v in state["surfels"].items()})
            keyframes = {}
            for entry in state["keyframes"]:
                pose = _as_pose(torch.from_numpy(np.array(entry["pose"])), "pose")
                K = torch.from_numpy(np.array(entry["K"])).to(self.device, torch.float32)
                image = None if entry["image"] is None else (
                    torch.from_numpy(np.array(entry["image"])).to(self.device, torch.float32) / 255.0)
                depth = None if entry["depth"] is None else torch.from_numpy(np.array(entry["depth"])).to(
                    self.device, torch.float32)
                archived = entry.get("archived")
                exposure = entry.get("exposure")
                keyframes[int(entry["id"])] = _Keyframe(
                    pose, K, int(entry["width"]), int(entry["height"]), image, depth,
                    None if archived is None else ArchivedKeyframe.from_dict(archived),
                    None if exposure is None else torch.from_numpy(np.array(exposure, np.float32)).to(self.device))
        except (KeyError, TypeError) as err:
            raise ValueError(f"malformed GaussianMap state: {err}") from err
        self._surfels = surfels.to(dtype=torch.float32)
        self._keyframes = keyframes
        voxel_size = state.get("voxel_size")
        self._voxel_size = None if voxel_size is None else float(voxel_size)
        background = state.get("background")
        if background is not None:  # the session kept one (a stereo session's map, MapConfig or keep_background)
            self._background = DirectionalBackground.from_state(background)
        self._archive_old_images()

    @classmethod
    def from_state_dict(cls, state: dict) -> GaussianMap:
        gmap = cls(MapConfig.from_dict(state["config"]))
        gmap.load_state_dict(state)
        return gmap

    # -- helpers -----------------------------------------------------------------------------------------------
    def _make_keyframe(self, pose: torch.Tensor, K: torch.Tensor, image: torch.Tensor,
                       depth: torch.Tensor | None) -> _Keyframe:
        image = torch.as_tensor(np.asarray(image) if not torch.is_tensor(image) else image).cpu()
        if image.ndim != 3 or image.shape[-1] != 3:
            raise ValueError(f"image must be [H, W, 3], got {tuple(image.shape)}")
        image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
        H, W = image.shape[:2]
        K = _as_K(K)
        if depth is not None:
            depth = torch.as_tensor(np.asarray(depth) if not torch.is_tensor(depth) else depth,
                                    dtype=torch.float32).cpu()
            if tuple(depth.shape) != (H, W):
                raise ValueError(f"depth must be [H, W] = {(H, W)}, got {tuple(depth.shape)}")
            depth = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0).to(self.device)
        return _Keyframe(pose, K.to(self.device), W, H, image.to(self.device), depth)

    def _fit_exposure(self, render: RenderResult, image: torch.Tensor) -> torch.Tensor | None:
        """The exposure of a keyframe's photo `image` fitted to a render (normalised colours) at its pose; None
        when the render covers less than MIN_EXPOSURE_COVERAGE of the view."""
        settings = self.config.refine
        covered = render.alpha >= settings.exposure_min_alpha
        if float(covered.float().mean()) < MIN_EXPOSURE_COVERAGE:
            return None
        # The composite itself, not divided by its alpha: refinement makes surfels translucent and brightens their
        # colours to match the photos (dividing made every ICL keyframe 3-5 % darker than the map).
        return fit_exposure(render.rgb, image, covered, settings.exposure_prior, threshold=settings.exposure_threshold,
                            shared=settings.exposure_shared)

    def _archive_old_images(self) -> None:
        """Keyframes that left the window: archive their images; beyond `archived_images`, the most redundant views
        are let go one by one (worker.mapping.archive_thinning)."""
        archived = [k for k in self.keyframe_ids[: -self.config.window] if self._keyframes[k].held]
        if len(archived) > self.config.archived_images:
            held = [k for k in self.keyframe_ids if self._keyframes[k].held]
            centres, axes = self._camera_centres_and_axes(held)
            scene_depth = self._scene_scale(self.keyframe_ids[-self.config.window:])
            let_go = thin(centres, axes, [held.index(k) for k in archived], self.config.archived_images, scene_depth)
            for index in let_go:
                self._keyframes[held[index]].drop()
            archived = [k for k in archived if self._keyframes[k].held]
        for kf_id in archived:
            self._keyframes[kf_id].archive()

    def _camera_centres_and_axes(self, kf_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """([N, 3] camera centres, [N, 3] unit optical axes) of keyframes, in world coordinates."""
        centres, axes = [], []
        for kf_id in kf_ids:
            _, R, t = sim3_decompose(self._keyframes[kf_id].pose.to(torch.float64))
            centres.append(t.cpu().numpy())
            axes.append(R[:, 2].cpu().numpy())
        return np.asarray(centres, np.float64).reshape(-1, 3), np.asarray(axes, np.float64).reshape(-1, 3)

    def _in_view(self, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
        """[N] bool: the map's surfels a render from this camera can touch."""
        if len(self._surfels) == 0:
            return torch.zeros(0, dtype=torch.bool, device=self.device)
        return visible_mask(self._surfels, viewmat, K, width, height)

    def _scene_scale(self, window: list[int]) -> float:
        """Median keyframe depth in world units (sets the position learning rate)."""
        depths = []
        for kf_id in window:
            kf = self._keyframes[kf_id]
            viewmat, _ = rigid_viewmat(kf.pose)
            mask = self._surfels.keyframe_ids == kf_id
            if mask.any():
                z = self._surfels.means[mask].double() @ viewmat[:3, :3].T.to(self.device) + viewmat[:3, 3].to(
                    self.device)
                depths.append(z[:, 2].float())
        if not depths:
            return 1.0
        return float(torch.cat(depths).median().clamp_min(1e-3))
