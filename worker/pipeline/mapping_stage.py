"""The mapping stage (paper 4.3, ORB-SLAM's LocalMapping in our terms): keyframes in, the 2DGS map out.

Per keyframe, in submission order, in the stage's own thread: build the surfel grid of a job that has none yet
(from the sensor's depth, or multi-view stereo's, `StereoBuilder`) -> hand a keyframe whose loop query waited for
its depth to loop closing -> voxelize -> prune -> fuse -> refine; pose updates after loop
closures move the map. Tracking never waits for it: `submit` never blocks, and the stage sheds work when it falls
behind (`MappingConfig.shed_backlog`, `merge_only_backlog`, `SlamConfig.queue_size`): fewer refinement iterations,
then merge only (finish() refines the whole map), then the oldest waiting keyframes are left out of the map. What it
shed and how far it lags (keyframes, seconds) is in `stats()`. The refinement it shed is owed: whenever its queue is
empty (`MappingConfig.idle_refine`), the stage refines the oldest keyframe it owes, with its window of that time, so
the live map catches up when the camera slows down or comes back to mapped places. All map access goes through one
lock, so renders and exports from other threads see the map between two refinement steps, never in the middle of one.
The final refinement (`refine_all`, up to its budget of tens of seconds) lets waiting renders and exports take the
lock between two of its steps: a client asking for the map while a session finishes waits one step, not the whole
refinement.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch

from protocol.codec import pack
from worker.config import MappingConfig
from worker.geometry import Intrinsics, sim3_inverse
from worker.mapping.exposure import apply_exposure
from worker.mapping.voxelize import voxelize
from worker.pipeline.depth_sources.multiview import StereoBuilder
from worker.pipeline.loop_stage import LoopQuery
from worker.pipeline.map_jobs import (
    KeyframeJob,
    PoseUpdateJob,
    build_gaussian_map,
    fusion_thresholds,
    job_from_state,
    job_state,
    unmerged_surfels,
)
from worker.pipeline.stage_thread import QueuedStage, StageThread
from worker.pipeline.stage_times import StageTimes
from worker.pipeline.surfel_init import grid_from_depth

SHED_KINDS = ("reduced", "merge_only", "dropped")
# How long the final refinement waits, between two steps, for readers to take the lock before it goes on (only a
# caller that already held the lock around it could keep them out that long).
READERS_WAIT_S = 1.0


class MappingStage(QueuedStage):
    """Map jobs in its own thread (or inline), with load shedding; serves renders and exports under a lock."""

    restarts = 0  # a thread is never replaced (a mapping process is: worker.pipeline.mapping_process)

    def __init__(self, cfg: MappingConfig, threaded: bool, max_backlog: int, device: str = "cpu",
                 timings: StageTimes | None = None) -> None:
        self.cfg = cfg
        self.max_backlog = max_backlog
        self.timings = timings or StageTimes()
        self.device = device
        self.map = build_gaussian_map(cfg, device)
        self._init_queue()
        self._readers_waiting = 0  # threads waiting for the lock to read the map
        self._readers_lock = threading.Lock()
        self.keyframes_mapped = 0
        self.busy_seconds = 0.0
        self.shed = dict.fromkeys(SHED_KINDS, 0)
        self.stereo: StereoBuilder | None = None  # builds multi-view depth jobs (`use_multiview_depth`)
        # Where keyframes whose loop query waited for their depth go once it is built (the loop-closing stage).
        self.loop_closing: Callable[[LoopQuery], None] | None = None
        self._waiting: deque[tuple[int, float]] = deque()  # (kf_id, submit time) of keyframe jobs not yet done
        self._waiting_lock = threading.Lock()
        self._owed: dict[int, int] = {}  # keyframe -> refinement iterations shed, oldest first
        self.caught_up = 0
        # Called in the stage's thread after each job done (with it) and each idle step (with None): a mapping
        # process reports its state to the session (worker.pipeline.mapping_process)
        self.on_progress: Callable[[KeyframeJob | PoseUpdateJob | None], None] | None = None
        self._stage = StageThread("mapping", self._handle_numbered, threaded,
                                  idle=self._catch_up if cfg.idle_refine else None)

    # -- submission (the tracking thread) ------------------------------------------------------------------------
    def submit(self, job: KeyframeJob | PoseUpdateJob) -> None:
        """Queue a job; never blocks (inline when not threaded)."""
        if isinstance(job, KeyframeJob):
            with self._waiting_lock:
                self._waiting.append((job.kf_id, time.monotonic()))
        super().submit(job)

    def use_multiview_depth(self, stereo: StereoBuilder) -> None:
        """The session's keyframe depth comes from multi-view stereo, built by `stereo`: prune new keyframes' views
        when `prune_multiview` asks for it, and keep a background behind the map when `background` does (see
        MappingConfig)."""
        self.stereo = stereo
        with self.lock:
            if self.cfg.prune_multiview:
                self.map.config.thresholds = fusion_thresholds(self.cfg, prune=True)
            if self.cfg.background:
                self.map.keep_background()

    def lag(self) -> tuple[int, float]:
        """(keyframes waiting to be mapped, seconds the oldest of them has waited)."""
        with self._waiting_lock:
            if not self._waiting:
                return 0, 0.0
            return len(self._waiting), time.monotonic() - self._waiting[0][1]

    def stats(self) -> dict[str, Any]:
        backlog, seconds = self.lag()
        return {"mapping_lag_keyframes": backlog, "mapping_lag_s": seconds, "keyframes_mapped": self.keyframes_mapped,
                "keyframes_shed": dict(self.shed), "mapping_busy_s": self.busy_seconds,
                "keyframes_caught_up": self.caught_up, "keyframes_owed": len(self._owed)}

    # -- work (the stage's thread) -------------------------------------------------------------------------------
    def _process(self, job: KeyframeJob | PoseUpdateJob) -> None:
        start = time.perf_counter()
        if isinstance(job, KeyframeJob):
            try:
                self._map_keyframe_job(job)
            finally:
                with self._waiting_lock:
                    if self._waiting and self._waiting[0][0] == job.kf_id:
                        self._waiting.popleft()
        else:
            with self.lock, self.timings.measure("map_loop_correction"):
                known = set(self.map.keyframe_ids)  # keyframes shed from the map have nothing to move
                self.map.apply_pose_updates({k: torch.as_tensor(v) for k, v in job.poses.items() if k in known})
                self._done(job)
        self.busy_seconds += time.perf_counter() - start
        if self.on_progress is not None:
            self.on_progress(job)

    def _backlog_behind(self) -> int:
        """Keyframe jobs waiting behind the one being processed."""
        with self._waiting_lock:
            return max(0, len(self._waiting) - 1)

    def _map_keyframe_job(self, job: KeyframeJob) -> None:
        backlog = self._backlog_behind()
        if backlog > self.max_backlog:  # too far behind: this keyframe stays out of the map
            with self.lock:
                self.shed["dropped"] += 1
                self._done(job)
            return
        if not job.built:  # outside the lock: renders go on meanwhile
            with self.timings.measure("map_depth"):
                self._build(job)
        if job.query_loops and job.depth is not None and self.loop_closing is not None:
            h, w = job.image.shape[:2]
            self.loop_closing(LoopQuery(job.kf_id, job.image.permute(2, 0, 1)[None],
                                        Intrinsics.from_matrix(job.K, w, h), job.depth, job.K))
        iterations = self._refine_iterations(backlog)
        self._wait_for_readers()
        with self.lock:
            self._map_keyframe(job, iterations)
            if self.cfg.idle_refine and iterations < self.cfg.refine_iterations:
                self._owed[job.kf_id] = self.cfg.refine_iterations - iterations
            self._done(job)

    def _build(self, job: KeyframeJob) -> None:
        """A job's surfel grid: from its views' multi-view depth, else from its sensor depth."""
        if job.views is not None:
            job.K, job.grid, job.depth = self.stereo.build(job)
        else:
            job.grid = grid_from_depth(job.image, job.depth, job.K)

    def _refine_iterations(self, backlog: int) -> int:
        """This keyframe's refinement iterations after load shedding."""
        iterations = self.cfg.refine_iterations
        if iterations == 0 or self.cfg.shed_backlog == 0 or backlog <= self.cfg.shed_backlog:
            return iterations
        if backlog > self.cfg.merge_only_backlog:
            self.shed["merge_only"] += 1
            return 0
        self.shed["reduced"] += 1
        return max(1, iterations * self.cfg.shed_backlog // backlog)

    def _map_keyframe(self, job: KeyframeJob, iterations: int) -> None:
        g = job.grid
        with self.timings.measure("map_merge"):
            vox = voxelize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], valid=g["valid"],
                           tau_d=self.cfg.tau_depth, keyframe_id=job.kf_id,
                           merged_scale_factor=self.cfg.merged_scale_factor
                           ) if self.cfg.voxel_block > 1 else unmerged_surfels(g, job.kf_id)
            self.map.add_keyframe(job.kf_id, torch.as_tensor(job.pose), job.K, job.image, vox.surfels,
                                  depth=job.depth)
        if iterations > 0:
            with self.timings.measure("map_refine"):
                self.map.refine(iterations)
        self.keyframes_mapped += 1

    def _catch_up(self) -> bool:
        """Idle work: refine the oldest keyframe whose refinement was shed; False when none is owed."""
        start = time.perf_counter()
        self._wait_for_readers()
        with self.lock:
            if not self._owed:
                return False
            kf_id = next(iter(self._owed))
            with self.timings.measure("map_catch_up"):
                self.map.refine_around(kf_id, self._owed.pop(kf_id))
        self.caught_up += 1
        self.busy_seconds += time.perf_counter() - start
        if self.on_progress is not None:
            self.on_progress(None)
        return True

    def refine_all(self, passes: int, budget_s: float | None = None, seed: int = 0,
                   train_poses: bool = False, on_step: Callable[[], None] | None = None) -> dict[int, np.ndarray]:
        """The end-of-run refinement: every surfel against every keyframe image the map still holds, `passes`
        times over those keyframes in an order drawn with `seed`, for at most `budget_s` seconds (None: the map's
        configured bound). With `train_poses`, the keyframes' cameras are refined too: returns, for each keyframe
        that moved, its world-frame motion T_new T_old^-1 (empty without). `on_step` is called after each step."""
        with self.lock, self.timings.measure("map_final_refine"):
            self._owed.clear()  # the whole map's refinement supersedes the keyframes' own
            if budget_s is not None and budget_s <= 0:
                return {}
            before = {k: self.map.keyframe_pose(k) for k in self.map.keyframe_ids}
            def after_step() -> None:
                self._let_readers_in()
                if on_step is not None:
                    on_step()

            self.map.refine_global(passes * self.map.held_images, seed=seed, budget_s=budget_s,
                                   after_step=after_step, train_poses=train_poses)
            after = {k: self.map.keyframe_pose(k) for k in before}
            return {k: (pose @ sim3_inverse(before[k])).numpy() for k, pose in after.items()
                    if not torch.equal(pose, before[k])}

    @contextlib.contextmanager
    def _reading(self) -> Iterator[None]:
        """The map's lock for a read, counted as waiting until it is taken (`_let_readers_in`)."""
        with self._readers_lock:
            self._readers_waiting += 1
        try:
            self.lock.acquire()
        finally:
            with self._readers_lock:
                self._readers_waiting -= 1
        try:
            yield
        finally:
            self.lock.release()

    def _wait_for_readers(self) -> None:
        """Before mapping a keyframe: renders, exports and snapshots waiting for the map go first (a lock is not
        fair: the stage's thread could take it again before a waiting reader wakes up)."""
        deadline = time.monotonic() + READERS_WAIT_S
        while self._readers_waiting and time.monotonic() < deadline:
            time.sleep(0.001)

    def _let_readers_in(self) -> None:
        """Between two steps of the final refinement (whose thread holds the lock once): the renders and exports
        waiting for the map take the lock in turn, then the refinement goes on."""
        deadline = time.monotonic() + READERS_WAIT_S
        while self._readers_waiting and time.monotonic() < deadline:
            self.lock.release()
            time.sleep(0.001)  # the waiting reader wakes up and takes the lock; acquire() then waits for its end
            self.lock.acquire()

    # -- reads ---------------------------------------------------------------------------------------------------
    def render(self, pose_c2w: np.ndarray, K: torch.Tensor, width: int, height: int,
               as_captured_at: int | None = None) -> Any:
        """The map seen from `pose_c2w`: exposure-normalised colours, or with `as_captured_at` (a frame index) the
        colours under the exposure the camera had at that frame (`GaussianMap.exposure_at`)."""
        with self._reading(), torch.no_grad():
            out = self.map.render(torch.as_tensor(pose_c2w), K, width, height)
            if as_captured_at is None:
                return out
            exposure = self.map.exposure_at(int(as_captured_at)).to(out.rgb.device)
            return out._replace(rgb=apply_exposure(out.rgb, exposure).clamp(0, 1))

    def num_gaussians(self) -> int:
        with self._reading():
            return int(self.map.num_gaussians)

    @property
    def held_images(self) -> int:
        """Keyframe images the map holds (what the final refinement's passes go over)."""
        return int(self.map.held_images)

    def to_ply_bytes(self) -> bytes:
        with self._reading():
            return self.map.to_ply_bytes()

    def snapshot_now(self, deliver: Callable[[Callable[[], bytes]], None],  # type: ignore[override]
                     external: dict[str, bytes] | None = None) -> None:
        """The stage's state as of now, packed (protocol.codec), handed to `deliver(make_part)` without waiting for
        the queue (QueuedStage.snapshot_now): the map between two steps and, as data, the jobs submitted so far and
        not in it yet, which a restored stage maps again (`load_state_dict`)."""
        def pack_state(jobs: list[KeyframeJob | PoseUpdateJob]) -> bytes:
            return pack({**self.state_dict(), "queued": [job_state(job) for job in jobs]}, external=external)

        super().snapshot_now(deliver, pack_state)

    def state_dict(self) -> dict:
        with self.lock:
            return {"map": self.map.state_dict(), "keyframes_mapped": self.keyframes_mapped,
                    "shed": dict(self.shed), "owed": [[k, v] for k, v in self._owed.items()],
                    "stereo": None if self.stereo is None else self.stereo.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        with self.lock:
            self.map.load_state_dict(d["map"])
            self.keyframes_mapped = int(d["keyframes_mapped"])
            self.shed.update({k: int(v) for k, v in (d.get("shed") or {}).items() if k in self.shed})
            self._owed = {int(k): int(v) for k, v in d.get("owed") or []}
            if self.stereo is not None and d.get("stereo") is not None:
                self.stereo.load_state_dict(d["stereo"])
        for item in d.get("queued") or []:  # submitted before the snapshot, not in its map: mapped now
            self.submit(job_from_state(item))
