"""Multi-view depth for keyframes of sessions whose frames carry none (posed RGB phones, visual odometry).

Two halves, one per thread. `MultiViewDepth` (the depth source, in the tracking thread) keeps the last frames'
images; each keyframe waits until `frames_after` more frames have arrived (neighbours on both sides see around
different occluders), then its job is made at the keyframe's current pose: the kept frames and their poses as
`StereoViews`, plain data. `StereoBuilder` (in the mapping stage) builds the job: the neighbours are chosen by
baseline and view angle (worker.depth.select_neighbours), and the plane-sweep depth (worker.depth.estimate_depth)
gives the surfel grid: confident pixels become surfels, the others none, or, with a `fill`, the learned model's
depth brought to their scale, or, with `propagate`, depth propagated from confident pixels of the same surface
(worker.depth.hole_fill) and, with `planes`, the depth of the dominant planes the recent keyframes' confident points
show, over the image regions that lie on them (worker.depth.world_planes: uniform floors and walls): those surfels
start at `PROPAGATED_OPACITY` of the usual opacity, so the refinement can fade and prune them where the photos
disagree, and the refinement's depth term sees the confident pixels only. With `borders`, a large textureless region
with no such support (a plain wall above its skirting board) takes the plane its border lies on, oriented by the
dominant planes (worker.depth.border_planes), at any coverage.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from worker.data.frame import Frame
from worker.depth import MultiViewDepthConfig, estimate_depth, scale_to_confident, select_neighbours
from worker.depth.border_planes import BorderSettings, fill_from_borders
from worker.depth.hole_fill import HoleFillSettings, fill_depth
from worker.depth.neighbours import looked_at_depth
from worker.depth.world_planes import PlaneMemory, PlaneSettings, fill_from_planes, image_regions
from worker.geometry import Intrinsics, se3_part
from worker.pipeline.depth_sources.base import DepthSource
from worker.pipeline.map_jobs import KeyframeJob, StereoViews
from worker.pipeline.session_camera import SessionCamera
from worker.pipeline.surfel_init import grid_from_depth
from worker.tracking.base import TrackingResult

log = logging.getLogger(__name__)

# Surfels on propagated depth start at this fraction of the usual initial opacity (a lower confidence).
PROPAGATED_OPACITY = 0.6
# Depth is propagated only where multi-view stereo covers at least this fraction of the keyframe.
MIN_COVERAGE_TO_PROPAGATE = 0.05


@dataclass
class PendingKeyframe:
    """A keyframe waiting for later frames: its id, K, and the depth range its pose source suggests."""

    kf_id: int
    K: np.ndarray
    depth_range: tuple[float, float] | None
    scene_depth: float | None
    query_loops: bool = False  # once its depth is built, the keyframe goes on to loop closing


DepthHint = tuple[tuple[float, float] | None, float | None]


def depth_hint(depth: np.ndarray | None, margin: float = 2.0) -> DepthHint:
    """(sweep range, typical depth) from a depth map (0 = unknown): a pose source's sparse depth (triangulated
    points) or the previous keyframe's multi-view depth; the range is widened by `margin` on both sides."""
    if depth is None:
        return None, None
    values = depth[np.isfinite(depth) & (depth > 0)]
    if values.size < 20:
        return None, None
    near, median, far = np.percentile(values, [2, 50, 98])
    return (float(near) / margin, margin * float(far)), float(median)


class MultiViewDepth(DepthSource):
    """The frame ring and the keyframes waiting for later frames (see the module docstring)."""

    name = "mvs"
    needs_later_frames = True

    def __init__(self, camera: SessionCamera, buffer_frames: int, frames_after: int,
                 builder: StereoBuilder | None = None) -> None:
        super().__init__()
        self.camera = camera
        self.buffer_frames = buffer_frames
        self.frames_after = frames_after
        self.builder = builder  # the mapping stage's half: read for its depth hint
        self.images: OrderedDict[int, np.ndarray] = OrderedDict()
        self.waiting: list[PendingKeyframe] = []

    def observe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult,
                intrinsics: Intrinsics | None) -> None:
        if tracking.tracked:  # a lost frame's held pose is not its own
            self.add_frame(frame.index, frame.image)

    def add_frame(self, index: int, image: np.ndarray) -> None:
        self.images[int(index)] = image
        while len(self.images) > self.buffer_frames:
            self.images.popitem(last=False)

    def add_keyframe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult | None,
                     query_loops: bool = False) -> None:
        self.add_keyframe_at(frame.index, self.camera.for_frame(frame).matrix().numpy(),
                             None if tracking is None else tracking.depth, query_loops)

    def add_keyframe_at(self, kf_id: int, K: np.ndarray, sparse_depth: np.ndarray | None,
                        query_loops: bool = False) -> None:
        """Keyframe `kf_id` (camera matrix `K`; `sparse_depth`: the points its pose source triangulated, if any)
        waits for its later frames."""
        depth_range, scene_depth = depth_hint(sparse_depth)
        self.waiting.append(PendingKeyframe(int(kf_id), np.asarray(K, np.float64), depth_range, scene_depth,
                                            query_loops))

    def add_last_frame(self, frame: Frame, pose: np.ndarray) -> bool:
        self.add_keyframe_at(frame.index, self.camera.for_frame(frame).matrix().numpy(), None)
        return True

    def scene_depth(self) -> float | None:
        """The typical depth of the newest keyframe whose depth was estimated (the keyframe selector's hint)."""
        return None if self.builder is None else self.builder.recent_hint[1]

    def jobs(self, pose_of: Callable[[int], np.ndarray], hold: bool = False, force: bool = False
             ) -> list[KeyframeJob]:
        for job in self.ready_jobs(pose_of, force):
            self.pending.append(job)
        return super().jobs(pose_of, hold, force)

    def move(self, changed: dict[int, np.ndarray]) -> None:
        super().move(changed)
        for waiting in self.waiting:
            changed.pop(waiting.kf_id, None)  # their jobs are made later, at the then current pose

    def ready_jobs(self, pose_of: Callable[[int], np.ndarray], force: bool = False) -> list[KeyframeJob]:
        """Jobs of the keyframes that have seen `frames_after` later frames (all of them when `force`); `pose_of`
        gives any kept frame's current world pose."""
        jobs = []
        newest = next(reversed(self.images)) if self.images else -1
        while self.waiting and (force or sum(i > self.waiting[0].kf_id for i in self.images) >= self.frames_after
                                or newest - self.waiting[0].kf_id > self.buffer_frames):
            job = self._job(self.waiting.pop(0), pose_of)
            if job is not None:
                jobs.append(job)
        return jobs

    def _job(self, kf: PendingKeyframe, pose_of: Callable[[int], np.ndarray]) -> KeyframeJob | None:
        ref_image = self.images.get(kf.kf_id)
        if ref_image is None:  # a keyframe the engine had to make while tracking was lost (the first frame)
            log.warning("keyframe %d: no tracked image kept, no multi-view depth", kf.kf_id)
            return None
        world_pose = pose_of(kf.kf_id)
        candidates = [i for i in self.images if i != kf.kf_id]
        views = StereoViews(ref_image, kf.K, se3_part(world_pose), float(np.cbrt(np.linalg.det(world_pose[:3, :3]))),
                            [self.images[i] for i in candidates], [se3_part(pose_of(i)) for i in candidates],
                            kf.depth_range, kf.scene_depth)
        image = torch.from_numpy(ref_image).to(torch.float32) / 255.0
        return KeyframeJob(kf.kf_id, world_pose, torch.from_numpy(kf.K).to(torch.float32), image, views=views,
                           query_loops=kf.query_loops)

    # ------------------------------------------------------------------------------------------ snapshot/restore
    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "indices": list(self.images), "images": list(self.images.values()),
                "pending": [{"kf_id": p.kf_id, "K": p.K, "depth_range": p.depth_range, "scene_depth": p.scene_depth,
                             "query_loops": p.query_loops} for p in self.waiting]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.images = OrderedDict((int(i), np.asarray(img, np.uint8)) for i, img in zip(state["indices"],
                                                                                          state["images"]))
        self.waiting = [PendingKeyframe(int(p["kf_id"]), np.asarray(p["K"], np.float64),
                                        None if p["depth_range"] is None else tuple(p["depth_range"]),
                                        p["scene_depth"], bool(p.get("query_loops", False)))
                        for p in state["pending"]]


class StereoBuilder:
    """The mapping stage's half: a keyframe's surfel grid from its `StereoViews` (see the module docstring)."""

    def __init__(self, config: MultiViewDepthConfig, fill: Callable[[np.ndarray], np.ndarray] | None = None,
                 propagate: bool = False, propagation: HoleFillSettings | None = None,
                 planes: PlaneSettings | None = None, borders: BorderSettings | None = None) -> None:
        """`fill(image) -> depth`: another depth (the model's) for the pixels stereo leaves without one, brought to
        the stereo depth's scale; else `propagate`: depth propagated into them from confident pixels of the same
        surface (with `propagation`'s settings), then, with `planes`, from the recent keyframes' dominant planes
        and, with `borders` too, for textureless regions from the planes their borders lie on
        (worker.depth.border_planes); neither leaves them without surfels."""
        self.config = config
        self.fill = fill
        self.propagation = (propagation or HoleFillSettings()) if propagate else None
        self.plane_memory = PlaneMemory(planes) if propagate and planes is not None else None
        self.borders = borders if self.plane_memory is not None else None
        self.fill_stats: list[float] = []  # fraction of each keyframe's pixels given a propagated depth
        # From the last keyframe whose depth was estimated: the hint for keyframes whose source gave none.
        self.recent_hint: DepthHint = (None, None)

    def build(self, job: KeyframeJob) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        """(K, surfel grid, confident depth) of a job with views. Jobs are built in keyframe order: one without a
        hint from its pose source takes the newest estimated keyframe's, read now."""
        views, kf_id = job.views, job.kf_id
        ref_image, K, ref_pose, scale, poses = views.image, views.K, views.pose, views.scale, views.poses
        depth_range, scene_depth = (views.depth_range, views.scene_depth) if views.scene_depth else self.recent_hint
        if scene_depth is None:  # no depth yet (posed RGB's first keyframes, textureless ones): where views look
            scene_depth = looked_at_depth(ref_pose, poses)
        chosen = select_neighbours(ref_pose, poses, self.config, scene_depth=scene_depth)
        neighbours = [(views.images[c], poses[c]) for c in chosen]
        estimate = estimate_depth(ref_image, K, ref_pose, neighbours, depth_range=depth_range, config=self.config)
        log.debug("keyframe %d: multi-view depth from %d views covers %.0f%%", kf_id, len(neighbours),
                  100 * estimate.coverage)
        if estimate.coverage > 0.2:
            self.recent_hint = depth_hint(estimate.depth, margin=3.0)
        confident = estimate.depth / scale  # world units -> the keyframe camera's (Sim(3) pose)
        surfel_depth, propagated = confident, None
        if self.fill is not None and estimate.coverage > MIN_COVERAGE_TO_PROPAGATE:
            filled = scale_to_confident(self.fill(ref_image), confident, estimate.confidence)
            surfel_depth = np.where(confident > 0, confident, filled).astype(np.float32)
        elif self.propagation is not None:
            if estimate.coverage > MIN_COVERAGE_TO_PROPAGATE:
                result = fill_depth(confident, ref_image, self.propagation)
                surfel_depth, propagated = result.depth, result.filled
            memory = self.plane_memory
            if memory is not None:  # in world units, as the poses
                memory.add(kf_id, estimate.depth, ref_pose, K)
            regions = None  # the image's regions, cut once for both plane fills
            if memory is not None and (self.borders is not None or estimate.coverage <= memory.settings.max_coverage):
                regions = image_regions(ref_image, memory.settings.edge_low, memory.settings.edge_high)
            if memory is not None and estimate.coverage <= memory.settings.max_coverage:
                planed, on_planes = fill_from_planes(surfel_depth * scale, ref_image, memory.planes(), ref_pose, K,
                                                     memory.settings, regions)
                surfel_depth = planed / scale
                propagated = on_planes if propagated is None else propagated | on_planes
            if self.borders is not None and memory.planes():  # only regions without support: any coverage
                bordered, on_borders = fill_from_borders(surfel_depth * scale, ref_image, memory.planes(), ref_pose,
                                                         K, self.borders, regions)
                surfel_depth = bordered / scale
                propagated = on_borders if propagated is None else propagated | on_borders
                confident = np.where(on_borders, 0, confident).astype(np.float32)  # stray matches replaced
            if propagated is not None:
                self.fill_stats.append(float(propagated.mean()))
                log.debug("keyframe %d: %.0f%% of the pixels given a propagated depth", kf_id, 100 * propagated.mean())
                propagated = torch.from_numpy(propagated)
        # The refinement's depth term sees the confident depth only.
        Kt = torch.from_numpy(K).to(torch.float32)
        grid = grid_from_depth(job.image, torch.from_numpy(surfel_depth), Kt, fill_holes=False)
        if propagated is not None:
            grid["opacities"] = torch.where(propagated, grid["opacities"] * PROPAGATED_OPACITY, grid["opacities"])
        return Kt, grid, torch.from_numpy(confident)

    def state_dict(self) -> dict[str, Any]:
        return {"planes": None if self.plane_memory is None else self.plane_memory.state_dict(),
                "recent_hint": [self.recent_hint[0], self.recent_hint[1]]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.plane_memory is not None and state.get("planes") is not None:
            self.plane_memory.load_state_dict(state["planes"])
        hint_range, hint_depth = state.get("recent_hint") or (None, None)
        self.recent_hint = (None if hint_range is None else tuple(hint_range), hint_depth)


def stereo_builder(config: Any, model: Any = None) -> StereoBuilder:
    """The mapping stage's half of multi-view depth with a session's settings (`config`: its SlamConfig; `model`
    fills holes with its depth where `input.mvs_fill` asks for it)."""
    cfg = config.input
    fill = None
    if cfg.mvs_fill == "model":
        from worker.pipeline.model_depth import ModelDepth

        fill = ModelDepth(model, config.frontend.long_side).depth
    return StereoBuilder(config.depth, fill, propagate=cfg.mvs_fill == "propagate",
                         planes=PlaneSettings() if cfg.mvs_planes else None,
                         borders=BorderSettings() if cfg.mvs_border_planes else None)
