"""The mapping process's side: one session's MappingStage, served over its channel.

The process waits for `init` (the session's SlamConfig), then serves until `close` or until the session's end of
the pipe is gone (the session's process exited or was killed: the mapping process exits too). Jobs (`submit`) go to
the stage's queue in arrival order; calls (`render`, `ply`, `wait_idle`, `refine_all`, `snapshot`, `map_state`,
`load`) run each in a thread of their own, so that a render waits for the map's lock while jobs keep arriving.
After each job and each idle refinement step the process reports the stage's state (`status`); a built keyframe
whose loop query waited for its depth goes back as a `loop_query`; a failure of the stage as `failed`.
"""

from __future__ import annotations

import logging
import os
import threading
from multiprocessing.connection import Connection
from typing import Any

import torch

from protocol.codec import unpack
from worker.config import SlamConfig
from worker.pipeline.depth_sources import stereo_builder
from worker.pipeline.loop_stage import LoopQuery
from worker.pipeline.map_jobs import KeyframeJob, PoseUpdateJob, job_from_state
from worker.pipeline.mapping_process.channel import Channel, ChannelClosed
from worker.pipeline.mapping_stage import MappingStage
from worker.pipeline.stage_thread import BACKGROUND_NICE
from worker.pipeline.stage_times import StageTimes

log = logging.getLogger(__name__)


def serve(conn: Connection) -> None:
    """The mapping process's entry point (see the module docstring)."""
    try:
        os.nice(BACKGROUND_NICE)  # tracking, in the session's process, gets a core first
    except OSError:
        pass
    channel = Channel(conn)
    try:
        init = channel.receive()
        if init["op"] != "init":
            raise ValueError(f"a mapping process starts with 'init', got {init['op']!r}")
        MappingServer(channel, SlamConfig.from_dict(init["config"])).run()
    except ChannelClosed:
        pass
    finally:
        channel.close()
        os._exit(0)  # the stage's threads are daemons: nothing to wait for


class MappingServer:
    """A MappingStage (threaded) and the loop that feeds it from the channel."""

    def __init__(self, channel: Channel, config: SlamConfig) -> None:
        torch.set_num_threads(config.num_threads)
        self.channel = channel
        self.config = config
        self.timings = StageTimes()
        self.stage = MappingStage(config.mapping, True, config.queue_size, config.device, self.timings)
        self.stage.on_progress = self._report
        self.stage.loop_closing = self._send_loop_query
        self.stage.on_failure(lambda err: self._send({"op": "failed", "error": f"the mapping stage failed: {err!r}"}))
        self.received = 0  # jobs received

    def run(self) -> None:
        while True:
            message = self.channel.receive()
            op = message["op"]
            if op == "submit":
                self.received += 1
                self.stage.submit(job_from_state(message["job"]))
            elif op == "load":  # inline: the jobs sent after it must queue behind the ones it restores
                self._load(message["data"], message["arrays"], set(message.get("queried") or []))
            elif op == "multiview":
                self.stage.use_multiview_depth(stereo_builder(self.config))
            elif op == "call" and message["name"] == "snapshot":  # cut now: it holds exactly the jobs received
                self._snapshot(message["id"], message["args"]["known"])
            elif op == "call":
                threading.Thread(target=self._call, args=(message,), name=f"mapping-{message['name']}",
                                 daemon=True).start()
            elif op == "close":
                self.stage.close()
                self.channel.send({"op": "closed"})
                return
            else:
                raise ValueError(f"unknown mapping-process message {op!r}")

    # -- what the process reports --------------------------------------------------------------------------------
    def _report(self, job: KeyframeJob | PoseUpdateJob | None) -> None:
        stage = self.stage
        with stage.lock:
            gaussians, held = int(stage.map.num_gaussians), int(stage.map.held_images)
        # `received` and `pending` read together: the session counts what it sent since as pending too
        received, pending = self.received, stage.pending - (job is not None)
        self._send({"op": "status", "received": received, "pending": pending,
                    "keyframe": job.kf_id if isinstance(job, KeyframeJob) else None,
                    "stats": stage.stats(), "gaussians": gaussians, "held_images": held,
                    "hint": None if stage.stereo is None else list(stage.stereo.recent_hint),
                    "timings": {"seconds": dict(self.timings.seconds), "counts": dict(self.timings.counts)}})

    def _send_loop_query(self, query: LoopQuery) -> None:
        self._send({"op": "loop_query", "kf_id": query.kf_id, "image": query.image, "K": query.K,
                    "depth": query.depth})

    def _send(self, message: dict[str, Any]) -> None:
        try:
            self.channel.send(message)
        except ChannelClosed:
            os._exit(0)  # the session is gone

    # -- calls ---------------------------------------------------------------------------------------------------
    def _call(self, message: dict[str, Any]) -> None:
        call_id, name, args = message["id"], message["name"], message.get("args") or {}
        try:
            value = getattr(self, f"_{name}")(call_id, **args)
            reply = {"op": "reply", "id": call_id, "value": value}
        except Exception as err:  # noqa: BLE001 - the session's side raises it
            log.exception("mapping process: call %s failed", name)
            reply = {"op": "reply", "id": call_id, "error": f"{type(err).__name__}: {err}"}
        self._send(reply)

    def _render(self, call_id: int, pose: Any, K: Any, width: int, height: int,
                as_captured_at: int | None) -> dict[str, Any]:
        out = self.stage.render(pose, torch.as_tensor(K, dtype=torch.float32), width, height, as_captured_at)
        return {"rgb": out.rgb, "depth": out.depth, "alpha": out.alpha, "normals": out.normals}

    def _ply(self, call_id: int) -> bytes:
        return self.stage.to_ply_bytes()

    def _wait_idle(self, call_id: int) -> None:
        self.stage.wait_idle()

    def _refine_all(self, call_id: int, passes: int, budget_s: float | None, seed: int,
                    train_poses: bool) -> list[list[Any]]:
        moved = self.stage.refine_all(passes, budget_s, seed, train_poses,
                                      on_step=lambda: self._send({"op": "step", "id": call_id}))
        self._report(None)
        return [[k, v] for k, v in moved.items()]

    def _snapshot(self, call_id: int, known: list[str]) -> None:
        """Cut the stage now (QueuedStage.snapshot_now: it is made between two work steps, by whichever of the stage's
        thread and a thread of its own comes first) and reply with it: the packed state, the digests of the arrays
        it refers to and those of them the session does not hold yet (`known`: those it holds)."""
        arrays: dict[str, bytes] = {}
        seen = set(known)

        def deliver(make: Any) -> None:
            try:
                data = make()
                reply = {"op": "reply", "id": call_id, "value": {
                    "bytes": data, "digests": list(arrays),
                    "arrays": {d: a for d, a in arrays.items() if d not in seen}}}
            except Exception as err:  # noqa: BLE001 - the session's side raises it
                log.exception("mapping process: a snapshot failed")
                reply = {"op": "reply", "id": call_id, "error": f"{type(err).__name__}: {err}"}
            self._send(reply)

        self.stage.snapshot_now(deliver, external=arrays)

    def _state(self, call_id: int) -> dict[str, Any]:
        return self.stage.state_dict()

    def _map_state(self, call_id: int) -> dict[str, Any]:
        with self.stage.lock:
            return self.stage.map.state_dict()

    def _load(self, data: bytes, arrays: dict[str, bytes], queried: set[int]) -> None:
        """The stage's state from a snapshot's map part; its queued keyframes whose loop query the session has
        already had (`queried`) do not ask again."""
        state = unpack(data, external=arrays)
        for item in state.get("queued") or []:
            if "keyframe" in item and int(item["keyframe"]["kf_id"]) in queried:
                item["keyframe"]["query_loops"] = False
        self.stage.load_state_dict(state)
        self._report(None)
