"""Multi-view depth for keyframes of sessions whose frames carry none (posed RGB phones, visual odometry).

The engine keeps the last frames' images here; each keyframe waits until `frames_after` more frames have arrived
(neighbours on both sides see around different occluders), then its neighbours are chosen by baseline and view
angle among the kept frames (worker.depth.select_neighbours) at their current poses, and a `KeyframeJob` is made
whose surfel grid the backend thread builds from the plane-sweep depth (worker.depth.estimate_depth): confident
pixels become surfels, the others none, or, with a `fill`, the learned model's depth brought to their scale, or,
with `propagate`, depth propagated from confident pixels of the same surface (worker.depth.hole_fill) and, with
`planes`, the depth of the dominant planes the recent keyframes' confident points show, over the image regions
that lie on them (worker.depth.world_planes: uniform floors and walls): those surfels start at
`PROPAGATED_OPACITY` of the usual opacity, so the refinement can fade and prune them where the photos disagree, and
the refinement's depth term sees the confident pixels only. With `borders`, a large textureless region with no
such support (a plain wall above its skirting board) takes the plane its border lies on, oriented by the dominant
planes (worker.depth.border_planes), at any coverage.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from worker.depth import MultiViewDepthConfig, estimate_depth, scale_to_confident, select_neighbours
from worker.depth.border_planes import BorderSettings, fill_from_borders
from worker.depth.hole_fill import HoleFillSettings, fill_depth
from worker.depth.neighbours import looked_at_depth
from worker.depth.world_planes import PlaneMemory, PlaneSettings, fill_from_planes, image_regions
from worker.engine.backend import KeyframeJob
from worker.engine.surfel_init import grid_from_depth
from worker.geometry import se3_part

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


class KeyframeDepth:
    """The frame ring and the keyframes waiting for their multi-view depth (see the module docstring)."""

    def __init__(self, config: MultiViewDepthConfig, buffer_frames: int, frames_after: int,
                 fill: Callable[[np.ndarray], np.ndarray] | None = None,
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
        self.buffer_frames = buffer_frames
        self.frames_after = frames_after
        self.images: OrderedDict[int, np.ndarray] = OrderedDict()
        self.pending: list[PendingKeyframe] = []
        # From the last keyframe whose depth was estimated: the hint for keyframes whose source gave none.
        self.recent_hint: DepthHint = (None, None)

    def add_frame(self, index: int, image: np.ndarray) -> None:
        self.images[int(index)] = image
        while len(self.images) > self.buffer_frames:
            self.images.popitem(last=False)

    def add_keyframe(self, kf_id: int, K: np.ndarray, sparse_depth: np.ndarray | None) -> None:
        depth_range, scene_depth = depth_hint(sparse_depth)
        self.pending.append(PendingKeyframe(int(kf_id), np.asarray(K, np.float64), depth_range, scene_depth))

    def ready_jobs(self, pose_of: Callable[[int], np.ndarray], force: bool = False) -> list[KeyframeJob]:
        """Jobs of the keyframes that have seen `frames_after` later frames (all of them when `force`); `pose_of`
        gives any kept frame's current world pose."""
        jobs = []
        newest = next(reversed(self.images)) if self.images else -1
        while self.pending and (force or sum(i > self.pending[0].kf_id for i in self.images) >= self.frames_after
                                or newest - self.pending[0].kf_id > self.buffer_frames):
            job = self._job(self.pending.pop(0), pose_of)
            if job is not None:
                jobs.append(job)
        return jobs

    def _job(self, kf: PendingKeyframe, pose_of: Callable[[int], np.ndarray]) -> KeyframeJob | None:
        ref_image = self.images.get(kf.kf_id)
        if ref_image is None:  # a keyframe the engine had to make while tracking was lost (the first frame)
            log.warning("keyframe %d: no tracked image kept, no multi-view depth", kf.kf_id)
            return None
        world_pose = pose_of(kf.kf_id)
        ref_pose = se3_part(world_pose)
        candidates = [i for i in self.images if i != kf.kf_id]
        poses = [se3_part(pose_of(i)) for i in candidates]
        images = [self.images[i] for i in candidates]
        config, K = self.config, kf.K
        image = torch.from_numpy(ref_image).to(torch.float32) / 255.0
        Kt = torch.from_numpy(K).to(torch.float32)

        scale = float(np.cbrt(np.linalg.det(world_pose[:3, :3])))

        def build() -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
            # Without a hint from the pose source, the newest estimated keyframe's, read now (builds run in keyframe
            # order): at job time the keyframes before this one may not be built yet.
            depth_range, scene_depth = (kf.depth_range, kf.scene_depth) if kf.scene_depth else self.recent_hint
            if scene_depth is None:  # no depth yet (posed RGB's first keyframes, textureless ones): where views look
                scene_depth = looked_at_depth(ref_pose, poses)
            chosen = select_neighbours(ref_pose, poses, config, scene_depth=scene_depth)
            neighbours = [(images[c], poses[c]) for c in chosen]
            estimate = estimate_depth(ref_image, K, ref_pose, neighbours, depth_range=depth_range, config=config)
            log.debug("keyframe %d: multi-view depth from %d views covers %.0f%%", kf.kf_id, len(neighbours),
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
                    memory.add(kf.kf_id, estimate.depth, ref_pose, K)
                regions = None  # the image's regions, cut once for both plane fills
                if memory is not None and (self.borders is not None
                                           or estimate.coverage <= memory.settings.max_coverage):
                    regions = image_regions(ref_image, memory.settings.edge_low, memory.settings.edge_high)
                if memory is not None and estimate.coverage <= memory.settings.max_coverage:
                    planed, on_planes = fill_from_planes(surfel_depth * scale, ref_image, memory.planes(), ref_pose,
                                                         K, memory.settings, regions)
                    surfel_depth = planed / scale
                    propagated = on_planes if propagated is None else propagated | on_planes
                if self.borders is not None and memory.planes():  # only regions without support: any coverage
                    bordered, on_borders = fill_from_borders(surfel_depth * scale, ref_image, memory.planes(),
                                                             ref_pose, K, self.borders, regions)
                    surfel_depth = bordered / scale
                    propagated = on_borders if propagated is None else propagated | on_borders
                    confident = np.where(on_borders, 0, confident).astype(np.float32)  # stray matches replaced
                if propagated is not None:
                    self.fill_stats.append(float(propagated.mean()))
                    log.debug("keyframe %d: %.0f%% of the pixels given a propagated depth", kf.kf_id,
                              100 * propagated.mean())
                    propagated = torch.from_numpy(propagated)
            # The refinement's depth term sees the confident depth only.
            grid = grid_from_depth(image, torch.from_numpy(surfel_depth), Kt, fill_holes=False)
            if propagated is not None:
                grid["opacities"] = torch.where(propagated, grid["opacities"] * PROPAGATED_OPACITY,
                                                grid["opacities"])
            return Kt, grid, torch.from_numpy(confident)

        return KeyframeJob(kf.kf_id, world_pose, Kt, image, grid={}, depth=None, build=build)

    # ------------------------------------------------------------------------------------------ snapshot/restore
    def state_dict(self) -> dict[str, Any]:
        return {"indices": list(self.images), "images": list(self.images.values()),
                "planes": None if self.plane_memory is None else self.plane_memory.state_dict(),
                "recent_hint": [self.recent_hint[0], self.recent_hint[1]],
                "pending": [{"kf_id": p.kf_id, "K": p.K, "depth_range": p.depth_range, "scene_depth": p.scene_depth}
                            for p in self.pending]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.images = OrderedDict((int(i), np.asarray(img, np.uint8)) for i, img in zip(state["indices"],
                                                                                          state["images"]))
        if self.plane_memory is not None and state.get("planes") is not None:
            self.plane_memory.load_state_dict(state["planes"])
        hint_range, hint_depth = state.get("recent_hint") or (None, None)
        self.recent_hint = (None if hint_range is None else tuple(hint_range), hint_depth)
        self.pending = [PendingKeyframe(int(p["kf_id"]), np.asarray(p["K"], np.float64),
                                        None if p["depth_range"] is None else tuple(p["depth_range"]),
                                        p["scene_depth"]) for p in state["pending"]]
