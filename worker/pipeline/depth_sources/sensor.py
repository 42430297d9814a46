"""Keyframe surfels from the frames' own depth (RGB-D): the grid is built in the mapping stage."""

from __future__ import annotations

import logging

import numpy as np
import torch

from worker.data.frame import Frame
from worker.pipeline.depth_sources.base import DepthSource
from worker.pipeline.map_jobs import KeyframeJob
from worker.pipeline.session_camera import SessionCamera
from worker.tracking.base import TrackingResult

log = logging.getLogger(__name__)


class SensorDepth(DepthSource):
    """Depth surfels: means from the unprojected depth, colour and orientation from the image and the depth. A
    session without intrinsics holds its jobs (`jobs(hold=True)`) until the pose source has estimated the camera:
    a job's K is the camera known when it is released."""

    name = "sensor"

    def __init__(self, camera: SessionCamera) -> None:
        super().__init__()
        self.camera = camera

    def add_keyframe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult | None,
                     query_loops: bool = False) -> None:
        if frame.depth is None:
            log.warning("keyframe %d carries no depth: it stays out of the map", frame.index)
            return
        given = self.camera.of_frame(frame)
        image = torch.from_numpy(frame.image).to(torch.float32) / 255.0
        depth = torch.from_numpy(np.asarray(frame.depth, np.float32))
        self.pending.append(KeyframeJob(frame.index, pose, None if given is None else given.matrix(), image,
                                        depth=depth))

    def add_last_frame(self, frame: Frame, pose: np.ndarray) -> bool:
        if frame.depth is None:
            return False
        self.add_keyframe(frame, pose, None)
        return True

    def _release(self, job: KeyframeJob, force: bool) -> KeyframeJob:
        if job.K is None:  # the camera estimated by now (or the best guess, when forced)
            h, w = job.image.shape[:2]
            job.K = self.camera.for_size(w, h).matrix()
        return job
