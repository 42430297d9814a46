"""`pose_mode: auto` without depth: the device's poses, or visual odometry seeded by them, chosen per session.

Where device poses agree with the images to what the images themselves allow (ICL's exact poses, COLMAP's), they
are the best odometry there is: `prior` (ICL posed RGB 28.7 dB, where visual odometry gives 27.5). Where they do not
(KITTI's GPS/IMU poses: the map on them renders 14.2 dB, on the visual odometry's 17.3), visual odometry should track
and the device poses only seed and constrain it: `seeded` (worker.tracking.seeded).

The session starts with the device's poses while the first frames judge them (worker.tracking.pose_agreement: the
three-view reprojection error with the device's poses over that of poses fitted to the same tracks from the images
alone, a scale-free ratio; `input.pose_choice`). The verdict comes within `within_frames` frames (on ICL and KITTI
after 18) as a `pose_source_chosen` event with its figures. Meanwhile the session makes no keyframe: at the verdict
the engine (worker.slam) takes the judged frames through the chosen source from the first, so `seeded` starts at
the first frame's device pose and no keyframe is ever made on device poses the images disagreed with.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.events import EngineEvent, PoseSourceChosen
from worker.geometry import Intrinsics
from worker.tracking.base import TrackingResult
from worker.tracking.device_clock import DeviceClock, clock_state, load_clock_state, retimed
from worker.tracking.pose_agreement import AgreementVerdict, PoseAgreement
from worker.tracking.seeded_config import PoseChoiceConfig
from worker.tracking.sources import DevicePoses

log = logging.getLogger(__name__)


class ChosenDevicePoses:
    """The device's poses (`prior`) until the first frames show they disagree with the images, then seeded visual
    odometry (module docstring). `new_seeded` builds the seeded source when it is chosen."""

    name = "device"

    def __init__(self, new_seeded: Callable[[], Any], config: PoseChoiceConfig | None = None) -> None:
        self.config = config or PoseChoiceConfig()
        self.new_seeded = new_seeded
        self.device = DevicePoses()
        self.seeded = None  # the seeded source, once chosen
        c = self.config
        self.agreement = PoseAgreement(c.step, c.triples, c.within_frames, c.max_ratio)
        self.choice: str | None = None if c.within_frames > 0 else "prior"  # "prior" or "seeded" once judged
        self.verdict: AgreementVerdict | None = None
        self.reason = None if self.choice is None else "pose_choice.within_frames is 0: not judged"
        self.device_clock: DeviceClock | None = None  # re-times the device poses for both sources, when set

    @property
    def judging(self) -> bool:
        """Whether the device poses are still being judged (a live stream should skip no frame meanwhile)."""
        return self.choice is None

    @property
    def scene_depth(self) -> float | None:
        """The scene's median depth the judging triangulated with the device poses (pose units), if any."""
        return self.agreement.scene_depth

    @property
    def source(self):
        """The source tracking now."""
        return self.device if self.seeded is None else self.seeded

    @property
    def estimated_intrinsics(self) -> Intrinsics | None:
        return getattr(self.source, "estimated_intrinsics", None)

    @property
    def calibrating(self) -> bool:
        return bool(getattr(self.source, "calibrating", False))

    def track(self, frame: Frame, intrinsics: Intrinsics | None) -> TrackingResult:
        frame = retimed(self.device_clock, frame, intrinsics)
        if self.seeded is not None:
            return self.seeded.track(frame, intrinsics)
        result = self.device.track(frame, intrinsics)
        if self.choice is not None:
            return result
        if frame.pose is None:  # a gap: triples do not span it
            self.agreement.forget_frames()
            return result
        if intrinsics is None:
            return self._decide("prior", frame.index, result, "no camera intrinsics to judge the poses with")
        if not self.agreement.add(frame.image, result.pose, intrinsics.matrix().numpy()):
            return result
        return self._judge(frame.index, result)

    def conclude(self, index: int) -> list[EngineEvent]:
        """The stream ended while judging: decide on the triples measured so far (the device's poses when too few);
        returns the `pose_source_chosen` event (none when already decided)."""
        if self.choice is not None:
            return []
        result = TrackingResult(np.eye(4))
        self._judge(index, result)
        return result.events

    def _judge(self, index: int, result: TrackingResult) -> TrackingResult:
        """Decide on the agreement's verdict; `result` (the device's) carries the event."""
        self.verdict = self.agreement.result
        if self.verdict is None:
            return self._decide("prior", index, result, "no frame triple with parallax to judge the poses by")
        v = self.verdict
        if v.triples < self.config.min_triples:
            return self._decide("prior", index, result,
                                f"only {v.triples} frame triple(s) with parallax within {self.agreement.frames} "
                                f"frames, fewer than {self.config.min_triples}: too few to judge the poses by")
        if v.agree:
            return self._decide("prior", index, result,
                                f"device poses agree with the images: {v.given_px:.2f} px three-view reprojection "
                                f"error, {v.ratio:.2f} times the images' own fit ({v.fitted_px:.2f} px), at most "
                                f"{v.max_ratio:g} allowed")
        self.seeded = self.new_seeded()  # it tracks the judged frames again from the first (SlamSystem)
        return self._decide("seeded", index, result,
                            f"device poses disagree with the images: {v.given_px:.2f} px three-view reprojection "
                            f"error, {v.ratio:.2f} times the images' own fit ({v.fitted_px:.2f} px), above "
                            f"{v.max_ratio:g}: visual odometry tracks, the device poses are priors")

    def _decide(self, choice: str, index: int, result: TrackingResult, reason: str) -> TrackingResult:
        self.choice, self.reason = choice, reason
        self.agreement.forget_frames()  # judging is over: its tracked frames' images are not needed any more
        log.info("frame %d: pose source %s (%s)", index, choice, reason)
        event = PoseSourceChosen(frame=int(index), pose_source=choice, reason=reason, **self._figures())
        result.events = [event, *result.events]
        return result

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        self.source.keyframe_added(retimed(self.device_clock, frame, None), pose)

    def keyframe_corrections(self) -> dict[int, np.ndarray]:
        """The chosen source's final adjustment of its keyframes (seeded visual odometry's), {} without one."""
        adjust = getattr(self.source, "keyframe_corrections", None)
        return {} if adjust is None else adjust()

    @property
    def final_adjustment(self):
        """The chosen source's final bundle adjustment once it ran (None before, or without one)."""
        return getattr(self.source, "final_adjustment", None)

    def summary(self) -> dict[str, Any]:
        """The choice (prior while still judging) and the figures it was made by."""
        return {"pose_source": self.choice or "prior",
                "pose_agreement": {"judged": self.choice is not None, "reason": self.reason, **self._figures()}}

    def _figures(self) -> dict[str, Any]:
        """The verdict's figures; `agree` is None when they rest on too few frame triples to judge by (the device
        poses are then kept by default, not found to agree or disagree)."""
        if self.verdict is None:
            return {}
        figures = self.verdict.to_dict()
        if self.verdict.triples < self.config.min_triples:
            figures["agree"] = None
        return figures

    def state_dict(self) -> dict[str, Any]:
        v = self.verdict
        return {"choice": self.choice, "reason": self.reason, "device": self.device.state_dict(),
                "agreement": self.agreement.state_dict(),
                "verdict": None if v is None else [v.given_px, v.fitted_px, v.triples, v.max_ratio],
                "seeded": None if self.seeded is None else self.seeded.state_dict(), **clock_state(self.device_clock)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        load_clock_state(self.device_clock, state)
        if "choice" not in state:  # a session snapshot by a worker without the choice: it used the device's poses
            self.device.load_state_dict(state)
            self.choice, self.reason = "prior", "resumed from a snapshot made before pose sources were judged"
            return
        self.choice, self.reason = state["choice"], state["reason"]
        self.device.load_state_dict(state["device"])
        self.agreement.load_state_dict(state["agreement"])
        v = state["verdict"]
        self.verdict = None if v is None else AgreementVerdict(float(v[0]), float(v[1]), int(v[2]), float(v[3]))
        if state["seeded"] is not None:
            self.seeded = self.new_seeded()
            self.seeded.load_state_dict(state["seeded"])
