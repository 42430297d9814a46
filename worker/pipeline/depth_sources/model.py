"""Keyframe surfels from the learned model's prediction (paper 4.3): its point map, confidence and Gaussian heads.

With the frames' depth, the means come from the depth instead (brought to the tracker's units when the poses are not
metric). Beside another pose source, the model predicts every frame too: the ratio of the given to the model's path
lengths converts its units to the poses', and surfels without depth wait for that ratio (`jobs`).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import torch

from worker.config import FrontendConfig
from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.pipeline.depth_sources.base import DepthSource
from worker.pipeline.map_jobs import KeyframeJob
from worker.pipeline.stage_times import StageTimes
from worker.pipeline.surfel_init import grid_from_prediction
from worker.tracking.base import TrackingResult
from worker.tracking.sources import ModelTracking


class ModelSurfels(DepthSource):
    """Surfels from the model (see the module docstring). `use_depth`: the frames' depth gives the means;
    `metric_poses`: the poses are in the depth's units (else the depth is scaled to the tracker's);
    `own_poses`: the model is the pose source (its surfels are in the poses' units already)."""

    name = "model"

    def __init__(self, model: ModelTracking, config: FrontendConfig, use_depth: bool, metric_poses: bool,
                 own_poses: bool, timings: StageTimes | None = None) -> None:
        super().__init__()
        self.model = model
        self.config = config
        self.use_depth = use_depth
        self.metric_poses = metric_poses
        self.own_poses = own_poses
        self.timings = timings or StageTimes()
        if use_depth:
            self.name = "sensor"
        self.path_given = 0.0  # path lengths of the given and the model's trajectories
        self.path_tracked = 0.0
        self._previous_poses: tuple[np.ndarray, np.ndarray] | None = None
        self._prediction: tuple[int, Any] | None = None  # (frame index, prediction) of the newest frame
        self._waits_for_scale: set[int] = set()  # jobs whose surfels are still in the model's units

    def observe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult, intrinsics: Intrinsics | None
                ) -> Any:
        prediction = tracking.prediction
        if prediction is None:  # the model predicts the surfels beside the pose source
            with self.timings.measure("frontend_inference"):
                prediction = self.model.predict(frame, intrinsics)
            self._accumulate_path(pose, prediction[1].pose_world.numpy())
        self._prediction = (frame.index, prediction)
        return prediction

    def _accumulate_path(self, given: np.ndarray, tracked: np.ndarray) -> None:
        if self._previous_poses is not None:
            g0, t0 = self._previous_poses
            self.path_given += float(np.linalg.norm(given[:3, 3] - g0[:3, 3]))
            self.path_tracked += float(np.linalg.norm(tracked[:3, 3] - t0[:3, 3]))
        self._previous_poses = (given.copy(), tracked.copy())

    def add_keyframe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult | None,
                     query_loops: bool = False) -> None:
        if self._prediction is None or self._prediction[0] != frame.index:
            raise RuntimeError(f"keyframe {frame.index}: the model has not seen it")
        prep, tracked = self._prediction[1]
        grid, depth = self._prediction_grid(frame, prep, tracked.surfels)
        image = prep.tensor[0].permute(1, 2, 0).contiguous()
        self.pending.append(KeyframeJob(frame.index, pose, self.model.model_intrinsics.matrix(), image, grid, depth))
        if depth is None and not self.own_poses:
            self._waits_for_scale.add(frame.index)

    def _ready(self, job: KeyframeJob, force: bool) -> bool:
        return force or job.kf_id not in self._waits_for_scale or self.path_tracked >= 1e-9

    def _release(self, job: KeyframeJob, force: bool) -> KeyframeJob:
        if job.kf_id in self._waits_for_scale:
            self._waits_for_scale.discard(job.kf_id)
            scale = self.path_given / self.path_tracked if self.path_tracked >= 1e-9 else 1.0
            job.grid = {**job.grid, "means": job.grid["means"] * scale, "scales": job.grid["scales"] * scale}
        return job

    def _frame_depth(self, frame: Frame, prep) -> torch.Tensor | None:
        """The frame's depth at model resolution (nearest neighbour, then the same crop), or None."""
        if not self.use_depth or frame.depth is None:
            return None
        h, w = frame.depth.shape
        new_w, new_h = round(w * prep.scale), round(h * prep.scale)
        depth = cv2.resize(np.asarray(frame.depth, np.float32), (new_w, new_h), interpolation=cv2.INTER_NEAREST)
        left, top, cw, ch = prep.crop
        return torch.from_numpy(np.ascontiguousarray(depth[top:top + ch, left:left + cw]))

    def _prediction_grid(self, frame: Frame, prep, surfels) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
        """A keyframe's surfel grid from the model; with depth, means from the depth brought to the tracker's
        units (the median ratio of predicted to measured depth), so the map stays consistent with the poses."""
        depth = self._frame_depth(frame, prep)
        if depth is not None and not self.metric_poses:
            valid = (depth > 0) & (surfels.points[..., 2] > 0)
            if bool(valid.any()):
                depth = depth * float((surfels.points[..., 2][valid].float() / depth[valid]).median())
        fc = self.config
        grid = grid_from_prediction(surfels.points.float(), surfels.conf.float(), surfels.quats.float(),
                                    surfels.scales.float(), surfels.opacity.float(), surfels.colors.float(),
                                    fc.min_confidence, depth=depth, K=self.model.model_intrinsics.matrix(),
                                    min_kept_fraction=fc.min_kept_fraction, ray_aligned=fc.ray_aligned_surfels)
        return grid, depth

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "path": [self.path_given, self.path_tracked],
                "previous_poses": None if self._previous_poses is None else list(self._previous_poses),
                "waits_for_scale": sorted(self._waits_for_scale)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.path_given, self.path_tracked = (float(v) for v in state.get("path") or (0.0, 0.0))
        previous = state.get("previous_poses")
        self._previous_poses = None if previous is None else tuple(np.asarray(p, np.float64) for p in previous)
        self._waits_for_scale = {int(k) for k in state.get("waits_for_scale") or []}
