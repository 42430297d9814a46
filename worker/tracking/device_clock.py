"""The device's pose clock against the camera's: each frame's device pose re-timed to the frame's true time.

A phone (ARKit/ARCore) or a motion-capture system stamps its poses with a clock 20-50 ms off the camera's: the pose
a frame carries is the camera's pose at `timestamp + offset`. `DeviceClock` keeps the device poses received with
their timestamps, measures the offset over the first frames with motion (worker.tracking.clock_offset; TUM fr1/xyz's
motion capture: +8 ms against its Kinect, ICL's rendered poses: 0) and gives each frame the device trajectory read
at `timestamp - offset`: slerp and linear between the received poses.

A positive offset reads between poses already received. A negative one reads after the newest pose: a live frame
cannot wait for the next, so the newest interval's motion continues at constant velocity, at most
`max_extrapolation_s` (50 ms: the -40 ms a phone shows is within it; beyond, a turn's guess would be worse than the
offset it corrects). Frames before the estimate get the poses with the given offset (`offset_s`, 0 by default), and
the measured one is reached by 1 ms a frame (SLEW_PER_FRAME_S), so that the device trajectory never jumps; frames seen
again (the judged start replays its frames) are read with the offset known then.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.tracking.clock_offset import ClockEstimate, PairTracker, estimate_offset
from worker.tracking.device_check import checked_device_pose
from worker.tracking.pose_interpolation import interpolate_poses
from worker.tracking.seeded_config import DeviceClockConfig

log = logging.getLogger(__name__)

KEEP_POSES = 90  # received poses kept once measured: the judged start's replay (30 frames) and the offset's reach
# A measured offset is reached at most this much per frame: switched at once, the device trajectory would jump by the
# offset's worth of motion mid-session, and seeded visual odometry measures its scale on the device's keyframe
# distances (TUM fr1/xyz posed RGB at -40 ms, switched at once: ATE 2.6 cm against 1.7 uncompensated; the same
# offset given from the first frame: 1.6)
SLEW_PER_FRAME_S = 0.001


class DeviceClock:
    """Re-times frames' device poses by the device clock's offset, given or measured (module docstring)."""

    def __init__(self, config: DeviceClockConfig | None = None, use_depth: bool = True,
                 background: bool = False) -> None:
        self.config = config or DeviceClockConfig()
        self.use_depth = use_depth  # the frames' depth measures the offset (metric reprojection), else epipolar
        self.background = background  # measure on a thread of its own (module docstring)
        self._worker: ThreadPoolExecutor | None = None
        self._estimates: list[tuple[Future[ClockEstimate], bool]] = []  # background estimates, with `final`
        self._pending: list[Future[None]] = []  # background frame hand-overs not yet done
        self.offset_s = float(self.config.offset_s)  # applied now
        self.target_offset_s = self.offset_s  # ... and once reached (SLEW_PER_FRAME_S)
        self.estimate: ClockEstimate | None = None
        self.measuring = self.config.mode == "estimate"
        self.frames = 0  # frames with a device pose received
        self.times: list[float] = []
        self.poses: list[np.ndarray] = []
        self.pairs = PairTracker()

    def pose_at(self, frame: Frame, intrinsics: Intrinsics | None) -> np.ndarray | None:
        """The device's pose at the frame's true time (None when the frame carries none). A frame newer than any seen
        is kept (and measured, with `intrinsics`, while measuring)."""
        if frame.pose is None:
            if self.measuring:
                self._run(self.pairs.forget_previous)
            return None
        pose = checked_device_pose(frame.pose, frame.index)
        t = float(frame.timestamp)
        self._collect(wait=False)
        if not self.times or t > self.times[-1]:
            self._receive(frame, t, pose, intrinsics)
            step = self.target_offset_s - self.offset_s
            self.offset_s += float(np.clip(step, -SLEW_PER_FRAME_S, SLEW_PER_FRAME_S))
        if self.offset_s == 0.0:
            return pose
        return interpolate_poses(np.asarray(self.times), np.stack(self.poses), np.asarray(t - self.offset_s),
                                 self.config.max_extrapolation_s)

    def _receive(self, frame: Frame, t: float, pose: np.ndarray, intrinsics: Intrinsics | None) -> None:
        self.times.append(t)
        self.poses.append(pose)
        self.frames += 1
        if self.measuring and intrinsics is not None:
            K = intrinsics.matrix().numpy().astype(np.float64)
            self._run(self.pairs.add, t, frame.image, frame.depth if self.use_depth else None, K)
            c = self.config
            if self.frames >= c.window_frames and (self.frames - c.window_frames) % c.retry_frames == 0:
                self._measure(final=self.frames + c.retry_frames > c.max_frames)
        elif self.measuring and self.frames >= self.config.max_frames:
            self._conclude(ClockEstimate(None, None, 0, "no camera intrinsics to measure the offset with"))
        if not self.measuring and len(self.times) > KEEP_POSES:
            del self.times[:-KEEP_POSES], self.poses[:-KEEP_POSES]

    def _run(self, task: Callable[..., None], *args: Any) -> None:
        """`task(*args)` now, or queued on the clock's thread (in order) with `background`."""
        if not self.background:
            task(*args)
            return
        self._pending = [f for f in self._pending if not f.done()]
        self._pending.append(self._executor().submit(task, *args))

    def _executor(self) -> ThreadPoolExecutor:
        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="device-clock")
        return self._worker

    def _measure(self, final: bool) -> None:
        c = self.config
        times, poses = np.asarray(self.times), np.stack(self.poses)  # as received so far (copies)
        if not self.background:
            self._take(estimate_offset(self.pairs.pairs, times, poses, c.search_s, c.max_uncertainty_s), final)
            return
        pairs = self.pairs

        def estimate() -> ClockEstimate:  # on the clock's thread, after the frames handed over before it
            return estimate_offset(list(pairs.pairs), times, poses, c.search_s, c.max_uncertainty_s)

        self._estimates.append((self._executor().submit(estimate), final))

    def _take(self, estimate: ClockEstimate, final: bool) -> None:
        if self.measuring and (estimate.offset_s is not None or final):
            self._conclude(estimate)

    def _collect(self, wait: bool) -> None:
        """Background estimates done (all of them, after the frames handed over, with `wait`) are taken in order."""
        if wait:
            for future in self._pending:
                future.result()
            self._pending = []
        while self._estimates and (wait or self._estimates[0][0].done()):
            future, final = self._estimates.pop(0)
            self._take(future.result(), final)
        if not self.measuring and self._worker is not None and not self._estimates:
            self._worker.shutdown(wait=False)
            self._worker, self._pending = None, []

    def _conclude(self, estimate: ClockEstimate) -> None:
        """Measuring is over: the estimate's offset from now on when trusted and distinct from zero (within twice
        its uncertainty a measured 0 is kept: exact poses stay untouched), else the given one."""
        self.estimate, self.measuring = estimate, False
        self.pairs = PairTracker()
        self._estimates = []
        if estimate.offset_s is not None and abs(estimate.offset_s) > 2 * (estimate.uncertainty_s or 0.0):
            self.target_offset_s = estimate.offset_s
        elif estimate.offset_s is not None:
            self.target_offset_s = 0.0
        log.info("device clock offset %.1f ms to apply (%s)", self.target_offset_s * 1000.0, estimate.reason)

    def finish_measuring(self) -> None:
        """The stream ended while measuring: the frames so far are all there is."""
        self._collect(wait=True)
        if self.measuring:
            self._measure(final=True)
            self._collect(wait=True)

    def summary(self) -> dict[str, Any]:
        """What the session reports: the offset applied, how it was measured (None while measuring)."""
        return {"mode": self.config.mode, "offset_ms": round(self.target_offset_s * 1000.0, 2),
                "applied_now_ms": round(self.offset_s * 1000.0, 2),
                "given_offset_ms": round(self.config.offset_s * 1000.0, 2),
                "measuring": self.measuring, "estimate": None if self.estimate is None else self.estimate.to_dict()}

    def state_dict(self) -> dict[str, Any]:
        self._collect(wait=True)  # the frames handed over and the estimates asked for are part of the state
        return {"offset_s": self.offset_s, "target_offset_s": self.target_offset_s, "measuring": self.measuring,
                "frames": self.frames,
                "estimate": None if self.estimate is None else self.estimate.to_dict(),
                "times": list(self.times), "poses": np.asarray(self.poses, np.float64).reshape(-1, 16),
                "pairs": self.pairs.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.offset_s, self.measuring = float(state["offset_s"]), bool(state["measuring"])
        self.target_offset_s = float(state.get("target_offset_s", self.offset_s))
        self.frames = int(state["frames"])
        self.estimate = None if state["estimate"] is None else ClockEstimate.from_dict(state["estimate"])
        self.times = [float(t) for t in state["times"]]
        self.poses = list(np.asarray(state["poses"], np.float64).reshape(-1, 4, 4))
        self.pairs = PairTracker()
        self.pairs.load_state_dict(state["pairs"])


def retimed(clock: DeviceClock | None, frame: Frame, intrinsics: Intrinsics | None) -> Frame:
    """`frame` with the device pose at its true time by `clock` (the frame itself without a clock or a pose): what a
    pose source reads device poses from (`device_clock` on DevicePoses, SeededTracking, ChosenDevicePoses)."""
    if clock is None or frame.pose is None:
        return frame
    pose = clock.pose_at(frame, intrinsics)
    return frame if pose is frame.pose else replace(frame, pose=pose)


def clock_state(clock: DeviceClock | None) -> dict[str, Any]:
    """The clock's part of its pose source's snapshot (nothing without a clock)."""
    return {} if clock is None else {"device_clock": clock.state_dict()}


def load_clock_state(clock: DeviceClock | None, state: dict[str, Any]) -> None:
    """The clock from its pose source's snapshot; one made before the clock keeps the given offset, unmeasured."""
    if clock is None:
        return
    if "device_clock" in state:
        clock.load_state_dict(state["device_clock"])
    else:
        clock.measuring = False
