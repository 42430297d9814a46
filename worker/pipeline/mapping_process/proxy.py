"""The session's side of a mapping process: the MappingStage interface, served by the process.

Jobs are sent as they come (`submit` never waits for the process); reads (`render`, `to_ply_bytes`, `map`), the final
refinement and snapshots are calls answered by it; its reports after each job keep the backlog, the counters, the
multi-view depth hint and the stage timings here up to date without a round trip. Keyframes whose loop query waited
for their depth come back from it and go to the loop-closing stage here.

A process that dies is replaced: the new one loads the last checkpoint of the map (a snapshot of the stage, taken
every `CHECKPOINT_EVERY` keyframes and with each of the session's own snapshots; `restart_log`) and is sent again
every job submitted after it, then every call that had no answer. A keyframe whose loop query was answered already
does not ask again. Tracking goes on meanwhile: jobs submitted during the restart queue behind the replayed ones.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from protocol.codec import pack, unpack
from worker.config import SlamConfig
from worker.geometry import Intrinsics
from worker.mapping.rasterize import RenderResult
from worker.pipeline.depth_sources.multiview import StereoBuilder
from worker.pipeline.loop_stage import LoopQuery
from worker.pipeline.map_jobs import KeyframeJob, PoseUpdateJob, build_gaussian_map, job_state
from worker.pipeline.mapping_process.channel import Channel, ChannelClosed
from worker.pipeline.mapping_process.launcher import start_mapping_process
from worker.pipeline.mapping_process.restart_log import Checkpoint, RestartLog
from worker.pipeline.mapping_stage import MappingStage
from worker.pipeline.stage_times import STAGES, StageTimes

log = logging.getLogger(__name__)

# Keyframes mapped after the last checkpoint of the map (the session's own snapshot or one of ours) before we take
# one: a restart replays about these. A worker snapshots its sessions more often than this (`snapshot_every`), so
# in the service these are the checkpoints: a map is packed once, not twice.
CHECKPOINT_EVERY = 8
CLOSE_WAIT_S = 10.0
MAX_RESTARTS = 3  # processes a session replaces; one more death fails its mapping stage
_STATS_BEFORE_A_REPORT = {"keyframes_mapped": 0, "keyframes_shed": {"reduced": 0, "merge_only": 0, "dropped": 0},
                          "mapping_busy_s": 0.0, "keyframes_caught_up": 0, "keyframes_owed": 0}


@dataclass
class _Call:
    call_id: int
    name: str
    args: dict[str, Any]
    on_step: Callable[[], None] | None = None
    done: threading.Event = field(default_factory=threading.Event)
    value: Any = None
    error: str | None = None


class MappingProcess:
    """A MappingStage in a process of its own (see the module docstring)."""

    name = "mapping"

    def __init__(self, config: SlamConfig, timings: StageTimes | None = None) -> None:
        self.config, self.cfg = config, config.mapping
        self.timings = timings or StageTimes()
        self.lock = threading.RLock()  # held by readers of `map` (a copy here): kept for MappingStage's interface
        self.stereo: StereoBuilder | None = None
        self.loop_closing: Callable[[LoopQuery], None] | None = None
        self.restarts = 0
        self._wire = threading.RLock()  # submissions, restarts and call sends go out in one order
        self._state = threading.Condition()
        self._submitted = 0  # jobs submitted since the session started (their numbers)
        self._sent = 0  # jobs sent to the current process
        self._report: dict[str, Any] = {"received": 0, "pending": 0, "stats": dict(_STATS_BEFORE_A_REPORT),
                                        "gaussians": 0, "held_images": 0}
        self._restart_log = RestartLog()  # the checkpoint and the jobs after it (under `_wire`)
        self._waiting: deque[tuple[int, float]] = deque()  # (kf_id, submit time) of keyframe jobs not done
        self._queried: set[int] = set()  # keyframes whose loop query came back
        self._calls: dict[int, _Call] = {}
        self._next_call = 0
        self._mapped_since_checkpoint = 0
        self._timing_base: dict[str, tuple[float, int]] = {}  # the stage timings of processes that died
        self._failure: str | None = None
        self._closing = False
        self._local: MappingStage | None = None  # the map, here, once the process is closed
        self._multiview = False
        self._process, self._channel = start_mapping_process(config)
        self._start_reader()

    # -- the MappingStage interface ------------------------------------------------------------------------------
    def submit(self, job: KeyframeJob | PoseUpdateJob) -> None:
        """Send a job to the process; never waits for it."""
        self.raise_if_failed()
        with self._wire:
            self._submitted += 1
            self._restart_log.record(self._submitted, job)
            if isinstance(job, KeyframeJob):
                with self._state:
                    self._waiting.append((job.kf_id, time.monotonic()))
            self._send_job(job)

    def use_multiview_depth(self, stereo: StereoBuilder) -> None:
        """Keyframe depth from multi-view stereo, built in the process (`stereo`: the session's builder, whose
        depth hint follows the process's)."""
        self.stereo = stereo
        with self._wire:
            self._multiview = True
            self._send({"op": "multiview"})

    @property
    def pending(self) -> int:
        """Jobs submitted and not done yet (those on their way to the process included)."""
        with self._state:
            return max(0, self._sent - self._report["received"] + self._report["pending"])

    def lag(self) -> tuple[int, float]:
        """(keyframes waiting to be mapped, seconds the oldest of them has waited)."""
        with self._state:
            if not self._waiting:
                return 0, 0.0
            return len(self._waiting), time.monotonic() - self._waiting[0][1]

    def stats(self) -> dict[str, Any]:
        backlog, seconds = self.lag()
        with self._state:
            stats = dict(self._report["stats"])
        return {**stats, "mapping_lag_keyframes": backlog, "mapping_lag_s": seconds,
                "mapping_process_restarts": self.restarts}

    @property
    def keyframes_mapped(self) -> int:
        with self._state:
            return int(self._report["stats"]["keyframes_mapped"])

    @property
    def busy_seconds(self) -> float:
        with self._state:
            return float(self._report["stats"]["mapping_busy_s"])

    @property
    def held_images(self) -> int:
        with self._state:
            return int(self._report["held_images"])

    def num_gaussians(self) -> int:
        if self._local is not None:
            return self._local.num_gaussians()
        with self._state:
            return int(self._report["gaussians"])

    def wait_idle(self) -> None:
        """Block until every submitted job is done; raise a failure of the process's stage."""
        self._call("wait_idle")
        self.raise_if_failed()

    def raise_if_failed(self) -> None:
        if self._failure is not None:
            raise RuntimeError(self._failure)

    def render(self, pose_c2w: np.ndarray, K: torch.Tensor, width: int, height: int,
               as_captured_at: int | None = None) -> RenderResult:
        """The map seen from `pose_c2w` (see MappingStage.render)."""
        if self._local is not None:
            return self._local.render(pose_c2w, K, width, height, as_captured_at)
        out = self._call("render", pose=np.asarray(pose_c2w, np.float64), K=torch.as_tensor(K).numpy(),
                         width=int(width), height=int(height),
                         as_captured_at=None if as_captured_at is None else int(as_captured_at))
        return RenderResult(*(torch.from_numpy(np.array(out[k])) for k in ("rgb", "depth", "alpha", "normals")))

    def to_ply_bytes(self) -> bytes:
        return self._local.to_ply_bytes() if self._local is not None else self._call("ply")

    @property
    def map(self) -> Any:
        """A copy of the process's map as of now (worker.mapping.GaussianMap), for packaging and inspection; once
        closed, the map itself."""
        if self._local is not None:
            return self._local.map
        gmap = build_gaussian_map(self.cfg, "cpu")
        gmap.load_state_dict(self._call("map_state"))
        return gmap

    def refine_all(self, passes: int, budget_s: float | None = None, seed: int = 0, train_poses: bool = False,
                   on_step: Callable[[], None] | None = None) -> dict[int, np.ndarray]:
        """The end-of-run refinement, in the process (see MappingStage.refine_all)."""
        moved = self._call("refine_all", on_step=on_step, passes=int(passes), budget_s=budget_s, seed=int(seed),
                           train_poses=bool(train_poses))
        return {int(k): np.asarray(v, np.float64) for k, v in moved}

    def snapshot_now(self, deliver: Callable[[Callable[[], bytes]], None],
                     external: dict[str, bytes] | None = None) -> None:
        """The stage's state as of now: the process cuts it after the jobs submitted so far, between two work
        steps, with those not done yet as data; `deliver(make_part)` gets it from a thread of its own. It is the
        checkpoint a restart loads too. Once closed, the map here is cut as a thread's is."""
        if self._local is not None:
            self._local.snapshot_now(deliver, external=external)
            return
        call, covers = self._request_checkpoint()

        def make() -> bytes:
            checkpoint = self._complete_checkpoint(call, covers)
            if external is not None:
                external.update(checkpoint.arrays)
                return checkpoint.data
            return pack(unpack(checkpoint.data, external=checkpoint.arrays))  # the arrays inside the bytes

        threading.Thread(target=deliver, args=(make,), name="mapping-snapshot", daemon=True).start()

    def load_state_dict(self, state: dict) -> None:
        """Continue from a snapshot's map part (unpacked): the process loads it; it is the checkpoint too."""
        data = pack(state)
        with self._wire:
            self._restart_log.start_from(data, self._submitted)
            self._send_load(self._restart_log.checkpoint)
        for item in state.get("queued") or []:
            if "keyframe" in item:
                with self._state:
                    self._waiting.append((int(item["keyframe"]["kf_id"]), time.monotonic()))

    def close(self) -> None:
        """Stop the process after the jobs sent (idempotent); the map comes here first, so that renders and exports
        of the finished session read it in this process (`_local`)."""
        if self._closing:
            return
        try:
            state = None if self._failure is not None else self._call("state")
        except RuntimeError:
            log.warning("mapping process: the map could not be taken before closing", exc_info=True)
            state = None
        if state is not None:
            local = MappingStage(self.cfg, False, self.config.queue_size, self.config.device, StageTimes())
            local.load_state_dict(state)
            self._local = local
        self._closing = True
        try:
            self._channel.send({"op": "close"})
        except ChannelClosed:
            pass
        self._process.join(CLOSE_WAIT_S)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._channel.close()
        self._fail_open_calls("the mapping process was closed")

    def _fail_open_calls(self, why: str, name: str | None = None) -> None:
        """Answer the calls still open (named `name`, or all) with the error `why`."""
        with self._state:
            lost = [call for call in self._calls.values() if name is None or call.name == name]
            for call in lost:
                del self._calls[call.call_id]
        for call in lost:
            call.error = why
            call.done.set()

    @property
    def checkpoint(self) -> Checkpoint:
        """The checkpoint of the map a replacement process would start from."""
        return self._restart_log.checkpoint

    @property
    def pid(self) -> int | None:
        """The process's id (tests and operators kill it to see a restart)."""
        return self._process.pid

    # -- calls ---------------------------------------------------------------------------------------------------
    def _call(self, name: str, on_step: Callable[[], None] | None = None, **args: Any) -> Any:
        if self._closing:
            raise RuntimeError(f"the mapping process is closed (its {name} cannot be served)")
        with self._state:
            self._next_call += 1
            call = _Call(self._next_call, name, args, on_step)
            self._calls[call.call_id] = call
        with self._wire:
            self._send_call(call)
        call.done.wait()
        if call.error is not None:
            raise RuntimeError(f"the mapping process's {name} failed: {call.error}")
        return call.value

    def _send_call(self, call: _Call) -> None:
        self._send({"op": "call", "id": call.call_id, "name": call.name, "args": call.args})

    def _send_job(self, job: KeyframeJob | PoseUpdateJob) -> None:
        state = job_state(job)
        if isinstance(job, KeyframeJob) and job.kf_id in self._queried:
            state["keyframe"]["query_loops"] = False  # asked already (a replay)
        self._sent += 1
        self._send({"op": "submit", "job": state})

    def _send(self, message: dict[str, Any]) -> None:
        try:
            self._channel.send(message)
        except ChannelClosed:
            pass  # the reader sees the process gone and restarts it; what was sent then goes again

    def _send_load(self, checkpoint: Checkpoint) -> None:
        self._send({"op": "load", "data": checkpoint.data, "arrays": checkpoint.arrays,
                    "queried": sorted(self._queried)})

    # -- checkpoints ---------------------------------------------------------------------------------------------
    def _request_checkpoint(self) -> tuple[_Call, int]:
        """Ask the process for a cut of its stage now; returns the call and how many jobs it covers. The arrays
        held here are not sent again (and stay held until the reply comes)."""
        with self._wire:
            with self._state:
                self._next_call += 1
                call = _Call(self._next_call, "snapshot", {"known": self._restart_log.held_for(self._next_call)})
                self._calls[call.call_id] = call
            covers = self._submitted
            self._send_call(call)
        return call, covers

    def _complete_checkpoint(self, call: _Call, covers: int) -> Checkpoint:
        """Wait for the cut `call` asked for; it becomes the checkpoint unless a later one already is."""
        call.done.wait()
        with self._wire:
            if call.error is not None:
                self._restart_log.forget(call.call_id)
                raise RuntimeError(f"the mapping process's snapshot failed: {call.error}")
            checkpoint, newest = self._restart_log.complete(call.call_id, call.value, covers)
            if newest:
                with self._state:
                    self._mapped_since_checkpoint = 0  # the session's own snapshots count: no extra cut is due
        return checkpoint

    def _checkpoint_in_background(self) -> None:
        call, covers = self._request_checkpoint()

        def complete() -> None:
            try:
                self._complete_checkpoint(call, covers)
            except RuntimeError:
                if self._closing:  # the session closed first: there is nothing left to keep
                    return
                log.warning("mapping process: a checkpoint failed", exc_info=True)
                with self._state:
                    self._mapped_since_checkpoint = 0  # try again as many keyframes later

        threading.Thread(target=complete, name="mapping-checkpoint", daemon=True).start()

    # -- what the process sends ----------------------------------------------------------------------------------
    def _start_reader(self) -> None:
        threading.Thread(target=self._read, args=(self._channel,), name="mapping-reader", daemon=True).start()

    def _read(self, channel: Channel) -> None:
        while True:
            try:
                message = channel.receive()
            except ChannelClosed:
                break
            if message["op"] == "closed":
                break
            self._handle(message)
        if not self._closing:
            self._restart()

    def _handle(self, message: dict[str, Any]) -> None:
        op = message["op"]
        if op == "status":
            self._on_status(message)
        elif op == "reply":
            with self._state:
                call = self._calls.pop(int(message["id"]), None)
            if call is not None:
                call.value, call.error = message.get("value"), message.get("error")
                call.done.set()
        elif op == "step":
            with self._state:
                call = self._calls.get(int(message["id"]))
            if call is not None and call.on_step is not None:
                call.on_step()
        elif op == "loop_query":
            self._on_loop_query(message)
        elif op == "failed":
            self._failure = str(message["error"])

    def _on_status(self, message: dict[str, Any]) -> None:
        checkpoint_due = False
        with self._state:
            self._report = message
            keyframe = message.get("keyframe")
            if keyframe is not None:
                if self._waiting and self._waiting[0][0] == keyframe:
                    self._waiting.popleft()
                self._mapped_since_checkpoint += 1
                if self._mapped_since_checkpoint == CHECKPOINT_EVERY:  # once, until a cut resets the count
                    checkpoint_due = True
            self._state.notify_all()
        if self.stereo is not None and message.get("hint") is not None:
            depth_range, scene_depth = message["hint"]
            self.stereo.recent_hint = (None if depth_range is None else tuple(depth_range), scene_depth)
        timings = message["timings"]
        for stage, seconds in timings["seconds"].items():
            if STAGES.get(stage, ("",))[0] != "backend":
                continue  # the process times mapping's stages only; the others are timed here
            base_seconds, base_count = self._timing_base.get(stage, (0.0, 0))
            self.timings.set_total(stage, base_seconds + seconds, base_count + int(timings["counts"][stage]))
        if checkpoint_due:
            self._checkpoint_in_background()

    def _on_loop_query(self, message: dict[str, Any]) -> None:
        kf_id = int(message["kf_id"])
        if kf_id in self._queried or self.loop_closing is None:
            return
        self._queried.add(kf_id)
        image = torch.from_numpy(np.array(message["image"]))
        K = torch.from_numpy(np.array(message["K"]))
        depth = None if message["depth"] is None else torch.from_numpy(np.array(message["depth"]))
        h, w = image.shape[-2:]
        self.loop_closing(LoopQuery(kf_id, image, Intrinsics.from_matrix(K, w, h), depth, K))

    # -- restarts ------------------------------------------------------------------------------------------------
    def _restart(self) -> None:
        """The process died: a new one, at the last checkpoint, sent every job after it and every open call."""
        log.warning("mapping process %s exited (code %s): restarting it from its checkpoint", self._process.pid,
                    self._process.exitcode)
        self._process.join(1.0)
        # a snapshot cut in the dead process is lost: its caller hears so (what it would cover changed)
        self._fail_open_calls("the mapping process exited before the snapshot was made", name="snapshot")
        with self._wire:
            if self._closing:
                return
            if self.restarts >= MAX_RESTARTS:  # a job that kills every process it reaches: the stage fails
                self._give_up(f"the mapping process died {self.restarts + 1} times (exit code "
                              f"{self._process.exitcode}); the session's map is lost")
                return
            self.restarts += 1
            self._timing_base = {stage: (self.timings.seconds[stage], self.timings.counts[stage])
                                 for stage, (thread, _, _) in STAGES.items() if thread == "backend"}
            self._channel.close(drain_s=0.0)
            try:
                self._process, self._channel = start_mapping_process(self.config)
            except (OSError, RuntimeError, ValueError) as err:
                self._give_up(f"the mapping process died and could not be restarted: {err}")
                return
            with self._state:
                self._sent = 0
                self._report = {**self._report, "received": 0, "pending": 0}
            if self._multiview:
                self._send({"op": "multiview"})
            if self._restart_log.checkpoint.data is not None:
                self._send_load(self._restart_log.checkpoint)
            for job in self._restart_log.jobs():
                self._send_job(job)
            with self._state:
                open_calls = sorted(self._calls.values(), key=lambda c: c.call_id)
            for call in open_calls:
                self._send_call(call)
            self._start_reader()

    def _give_up(self, why: str) -> None:
        """The stage fails: the session's next frame raises `why`; open calls are answered with it."""
        log.error("mapping process: %s", why)
        self._failure = why
        self._fail_open_calls(why)
