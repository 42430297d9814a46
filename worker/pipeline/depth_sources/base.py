"""What every depth source shares: the keyframe jobs it made and has not handed to mapping yet."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.pipeline.map_jobs import KeyframeJob
from worker.tracking.base import TrackingResult


class DepthSource:
    """Where a session's keyframe surfels come from (see worker.pipeline.depth_sources). It sees every frame
    (`observe`) and every keyframe (`add_keyframe`), owns the jobs it made until mapping takes them (`jobs`), and
    moves them with loop corrections (`move`). Jobs are data: `state_dict` carries the waiting ones."""

    name = "none"
    needs_later_frames = False  # a keyframe's job needs frames after it (multi-view stereo)

    def __init__(self) -> None:
        self.pending: list[KeyframeJob] = []

    def observe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult, intrinsics: Intrinsics | None
                ) -> Any:
        """A tracked frame; returns the learned model's prediction for it when this source makes one."""
        return None

    def add_keyframe(self, frame: Frame, pose: np.ndarray, tracking: TrackingResult | None,
                     query_loops: bool = False) -> None:
        """Keyframe `frame` at world pose `pose` (c2w): its job, now or once what it needs has arrived."""
        raise NotImplementedError

    def add_last_frame(self, frame: Frame, pose: np.ndarray) -> bool:
        """The session's newest view at its end, mapped like a keyframe where this source can; whether it will."""
        return False

    def scene_depth(self) -> float | None:
        """A typical scene depth this source knows and tracking does not (the keyframe selector's hint)."""
        return None

    def jobs(self, pose_of: Callable[[int], np.ndarray], hold: bool = False, force: bool = False
             ) -> list[KeyframeJob]:
        """The jobs ready for mapping now, oldest first (none while `hold`, e.g. the camera is being calibrated;
        every one when `force`). `pose_of` gives a tracked frame's current world pose."""
        if hold and not force:
            return []
        ready = []
        while self.pending and self._ready(self.pending[0], force):
            ready.append(self._release(self.pending.pop(0), force))
        return ready

    def _ready(self, job: KeyframeJob, force: bool) -> bool:
        return True

    def _release(self, job: KeyframeJob, force: bool) -> KeyframeJob:
        return job

    def move(self, changed: dict[int, np.ndarray]) -> None:
        """A loop correction: the waiting jobs take their keyframes' new poses (taken out of `changed`, which the
        map applies to what it holds)."""
        for job in self.pending:
            if job.kf_id in changed:
                job.pose = changed.pop(job.kf_id)

    def state_dict(self) -> dict[str, Any]:
        return {"jobs": [job.state_dict() for job in self.pending]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pending = [KeyframeJob.from_state(job) for job in state.get("jobs") or []]
