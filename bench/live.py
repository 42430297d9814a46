"""Live streaming through the real service (issue 24 points 2 and 4): a client paces frames at a phone's rate over
the WebSocket without waiting for poses, into `flashmono serve`'s stack (private Redis, the gateway under uvicorn,
one SLAM worker at nice 10, all on this machine).

Per frame it records capture time (start + seq / fps), send time, ack, pose or `skipped` answer, and reports:
pose latency (capture -> pose received, and last send -> pose) p50/p95/p99, frames acked / with a pose / skipped,
re-sends after `backpressure`, message types seen (unknown ones counted, never fatal), `finish` time, the session's
mapping lag (`mapping_lag_keyframes`, `mapping_lag_s`, `frames_skipped` of GET /v1/sessions/{id} when the engine
reports them), the worker's and gateway's RSS over time, and at the end the ATE against the sequence's ground truth
(SE(3)-aligned with depth or device poses, Sim(3) for RGB only) and the PSNR of rendered non-keyframes, beside the
offline `flashmono run` engine (worker.offline.run_sequence) on the same frames. `--kill-at F` SIGKILLs the
owning worker once a fraction F of the frames is sent and poses are flowing (5 received), starts a new one at once
(as `flashmono serve`'s supervisor does) and reports the gap until poses resume and whether any acked frame was
lost or answered twice. The posed modes send the sequence's poses as a phone's AR poses would come: the session
judges them over its first frames and replays those frames through the chosen source, and the summary's
`pose_source_chosen` says what that verdict cost the frame it came with.

`python -m bench live [--source PATH] [--mode rgbd|rgb|posed-rgb|posed-rgbd] [--size 320x240] [--fps 30]
[--frames N] [--kill-at 0.5] [--no-offline] [--plot PATH] [--json PATH] [--write-results]`; PATH defaults to
tests/data/icl_mini (any `worker.data.open_source` path with ground truth, e.g.
/work/shared/data/icl_livingroom1_micro or a TUM folder).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import os
import tempfile
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.record import JOURNAL_INBOX, Recorder
from bench.takeover import kill_when, takeover_phases

ROOT = Path(__file__).resolve().parent.parent
MINI = ROOT / "tests" / "data" / "icl_mini"
RESULTS = JOURNAL_INBOX  # bench/RESULTS.md is generated (python -m bench scoreboard): narrative goes to the journal
SAMPLE_S = 0.5  # session record and RSS sampling period
IMMEDIATE = ("ack", "error")  # the answers each binary frame gets at once, in order


# --------------------------------------------------------------------------------------------------- the client
@dataclass
class FrameLog:
    """What happened to one frame on the wire (monotonic seconds; None: never)."""

    capture: float = 0.0
    sent: float | None = None
    sends: int = 0
    acked: float | None = None
    pose: float | None = None
    poses: int = 0  # pose messages for this seq (more than one is a duplicate)
    skipped: float | None = None
    error: str | None = None


@dataclass
class LiveRun:
    """A paced, pipelined stream of pre-encoded frame messages and everything it observed."""

    url: str
    messages: list[bytes]
    fps: float
    frames: list[FrameLog] = field(default_factory=list)
    types: collections.Counter = field(default_factory=collections.Counter)
    events: list[tuple[float, dict]] = field(default_factory=list)  # loop_closed, tracking_lost, ... as received
    rewinds: int = 0
    start: float = 0.0
    finish_sent: float | None = None
    finished: float | None = None
    failure: str | None = None

    def __post_init__(self) -> None:
        self.frames = [FrameLog() for _ in self.messages]
        self._next = 0
        self._epoch = 0
        self._resume_at = 0.0
        self._streak = 0  # rewinds since the last accepted frame: the back-off doubles with each
        self._probing = False  # after a rewind, frames go one at a time until the server accepts one
        self._unanswered: collections.deque[tuple[int, int]] = collections.deque()
        self._done = asyncio.Event()

    async def run(self, timeout_s: float) -> None:
        """Send every frame at its capture time (later after a rewind), then `finish`; wait for `finished`."""
        import websockets

        async with websockets.connect(self.url, max_size=None, compression=None, open_timeout=60,
                                      ping_interval=20, ping_timeout=120) as ws:
            reader = asyncio.create_task(self._read(ws))
            self.start = time.monotonic() + 0.2
            for i, log in enumerate(self.frames):
                log.capture = self.start + i / self.fps
            deadline = self.start + timeout_s
            while time.monotonic() < deadline and self.failure is None and not reader.done():
                if self._next >= len(self.messages):
                    if all(f.acked is not None or f.error for f in self.frames) and not self._unanswered:
                        break
                    await asyncio.sleep(0.01)
                    continue
                seq = self._next
                wait = max(self.frames[seq].capture, self._resume_at) - time.monotonic()
                if wait > 0 or (self._probing and self._unanswered):  # after a rewind: one frame until accepted
                    await asyncio.sleep(wait if wait > 0 else 0.005)
                    continue
                self._unanswered.append((seq, self._epoch))
                self._next += 1
                log = self.frames[seq]
                log.sent, log.sends = time.monotonic(), log.sends + 1
                await ws.send(self.messages[seq])
            self.finish_sent = time.monotonic()
            await ws.send(json.dumps({"type": "finish"}))
            try:
                await asyncio.wait_for(self._done.wait(), timeout=max(1.0, deadline - time.monotonic()))
            except TimeoutError:
                self.failure = self.failure or "no finished message before the timeout"
            reader.cancel()

    async def _read(self, ws) -> None:
        try:
            async for raw in ws:
                now = time.monotonic()
                try:
                    message = json.loads(raw)
                except ValueError:
                    self.types["<not json>"] += 1
                    continue
                kind = str(message.get("type"))
                self.types[kind] += 1
                seq = message.get("seq")
                if kind in IMMEDIATE and seq is not None and self._unanswered:
                    self._immediate(kind, int(seq), message, now)
                elif kind == "error":  # a result error (the worker could not use the frame) or a stream error
                    if seq is not None and 0 <= int(seq) < len(self.frames):
                        self.frames[int(seq)].error = str(message.get("code"))
                    else:
                        self.failure = f"stream error: {message}"
                elif kind == "pose" and seq is not None:
                    log = self.frames[int(seq)]
                    log.poses += 1
                    log.pose = log.pose or now
                elif kind == "skipped" and seq is not None:
                    self.frames[int(seq)].skipped = self.frames[int(seq)].skipped or now
                elif kind == "finished":
                    self.finished = now
                    self._done.set()
                    return
                else:
                    self.events.append((now, message))
        except Exception as err:  # a closed socket without finished: reported, the run ends
            self.failure = self.failure or f"stream closed: {err!r}"
        finally:
            self._done.set()

    def _immediate(self, kind: str, seq: int, message: dict, now: float) -> None:
        expected, epoch = self._unanswered.popleft()
        if expected != seq:
            self.failure = f"answer for seq {seq} while {expected} was the oldest unanswered"
            return
        log = self.frames[seq]
        if kind == "ack":
            log.acked = now
            log.error = None
            self._streak = 0
            self._probing = False
        elif message.get("code") == "backpressure":
            if epoch == self._epoch:  # the first refusal since the last rewind: rewind as the protocol says
                self._epoch += 1
                self.rewinds += 1
                self._next = int(message.get("resend_from", seq))
                self._resume_at = now + min(1.0, 0.05 * 2 ** self._streak)
                self._streak += 1
                self._probing = True
        else:
            log.error = str(message.get("code"))


# ------------------------------------------------------------------------------------------------ the stack
class Sampler:
    """Polls the session record and the processes' RSS every SAMPLE_S seconds while the stream runs."""

    def __init__(self, base_url: str, session_id: str, stack) -> None:
        self.base_url, self.session_id, self.stack = base_url, session_id, stack
        self.rows: list[dict[str, Any]] = []
        self._stop = asyncio.Event()

    async def run(self) -> None:
        import httpx

        async with httpx.AsyncClient(base_url=self.base_url, timeout=10) as http:
            while not self._stop.is_set():
                row: dict[str, Any] = {"t": time.monotonic(), "worker_rss": _rss([w.pid for w in self.stack.workers
                                                                               if w.poll() is None]),
                                       "gateway_rss": _rss([self.stack.gateway.pid])}
                try:
                    record = (await http.get(f"/v1/sessions/{self.session_id}")).json()
                    for key in ("frames_received", "frames_processed", "keyframes", "status", "worker",
                                "mapping_lag_keyframes", "mapping_lag_s", "frames_skipped"):
                        if key in record:
                            row[key] = record[key]
                except Exception as err:  # the record is best effort while a worker dies
                    row["record_error"] = repr(err)
                self.rows.append(row)
                try:
                    await asyncio.wait_for(self._stop.wait(), timeout=SAMPLE_S)
                except TimeoutError:
                    pass

    def stop(self) -> None:
        self._stop.set()


def _rss(pids: list[int]) -> float:
    """Summed resident set size of `pids` in MiB (psutil when installed, else /proc), with the proportional set
    size of every process they started (sessions' mapping processes, through a fork server)."""
    from worker.runtime.memory import descendants, proportional_mb

    total = sum(proportional_mb(child) for pid in pids for child in descendants(pid)) * 2**20
    for pid in pids:
        try:
            import psutil

            total += psutil.Process(pid).memory_info().rss
        except ImportError:
            try:
                for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) * 1024
            except OSError:
                pass
        except Exception:  # the process just exited
            pass
    return total / 2**20


# ---------------------------------------------------------------------------------------------------- frames
MODES = ("rgbd", "rgb", "posed-rgb", "posed-rgbd")


def mode_inputs(mode: str) -> tuple[bool, bool]:
    """(depth sent, device poses sent) for a `--mode`."""
    return mode.endswith("rgbd"), mode.startswith("posed")


def load_frames(source: str, size: tuple[int, int], max_frames: int | None, with_depth: bool,
                with_pose: bool = False):
    from worker.data import open_source

    src = open_source(source, resize=size, max_frames=max_frames, use_gt_depth=True, use_gt_poses=with_pose)
    frames = list(src)
    for frame in frames:
        if not with_depth:
            frame.depth = None
        if not with_pose:
            frame.pose = None
    if not frames:
        raise SystemExit(f"{source} yielded no frames")
    return frames, src.intrinsics


def encode(frames, with_depth: bool, with_pose: bool = False) -> list[bytes]:
    from client.streaming import WireOptions, encode_frame_message

    wire = WireOptions(send_intrinsics=True, send_depth=with_depth, send_pose=with_pose)
    return [encode_frame_message(f, i, wire) for i, f in enumerate(frames)]


def ate(poses: dict[int, np.ndarray], frames, rgb_only: bool) -> float | None:
    from worker.eval import absolute_trajectory_error

    pairs = [(poses[i], f.gt_pose) for i, f in enumerate(frames) if i in poses and f.gt_pose is not None]
    if len(pairs) < 3:
        return None
    est = np.stack([p for p, _ in pairs])
    gt = np.stack([np.asarray(g, np.float64) for _, g in pairs])
    return float(absolute_trajectory_error(est, gt, "sim3" if rgb_only else "se3").rmse)


# ------------------------------------------------------------------------------------------------- one case
async def stream_case(stack, frames, intrinsics, messages: list[bytes], args) -> dict[str, Any]:
    import httpx

    from worker.geometry import se3_part

    async with httpx.AsyncClient(base_url=stack.base_url, timeout=120) as http:
        k = intrinsics
        # as openapi.yaml tells a mobile app: intrinsics, skip_frames and frame_rate; a preset only when asked
        body = {"name": "bench-live", "skip_frames": not args.every_frame, "frame_rate": args.fps,
                "intrinsics": {"width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy}}
        if args.preset:
            body["preset"] = args.preset
        if args.tracking_side:
            body["tracking_side"] = args.tracking_side
        body.update(getattr(args, "session_fields", None) or {})  # e.g. a saved map to run in (bench.map_reuse)
        created = await http.post("/v1/sessions", json=body)
        created.raise_for_status()
        sid = created.json()["id"]
        run = LiveRun(f"{stack.ws_url}/v1/sessions/{sid}/stream", messages, args.fps)
        sampler = Sampler(stack.base_url, sid, stack)
        sampling = asyncio.create_task(sampler.run())
        kill: dict[str, Any] = {}
        killer = None
        if args.kill_at is not None:
            killer = asyncio.create_task(_kill_when_running(run, int(args.kill_at * len(messages)), stack, http, sid,
                                                            kill))
        probe: dict[str, Any] = {}
        finishing = (asyncio.create_task(_map_while_finishing(run, http, sid, probe)) if args.map_while_finishing
                     else None)
        await run.run(args.timeout_s)
        if finishing is not None:
            await asyncio.wait_for(finishing, timeout=120)
        sampler.stop()
        await sampling
        if killer is not None:
            killer.cancel()
        record = (await http.get(f"/v1/sessions/{sid}")).json()
        if kill.get("at_wall"):
            kill["phases"] = takeover_phases(stack.redis_url, sid, kill["at_wall"])
        trajectory = (await http.get(f"/v1/sessions/{sid}/trajectory", params={"which": "all"})).json()
        keyframes = (await http.get(f"/v1/sessions/{sid}/trajectory", params={"which": "keyframes"})).json()
        poses = {int(p["seq"]): np.asarray(p["pose"], np.float64).reshape(4, 4) for p in trajectory["poses"]}
        keyframe_seqs = {int(p["seq"]) for p in keyframes["poses"]}
        psnr_value, psnr_frames = None, 0
        if args.psnr_every > 0 and record.get("status") == "finished":
            psnr_value, psnr_frames = await _live_psnr(http, sid, frames, poses, keyframe_seqs, intrinsics,
                                                       args.psnr_every, se3_part)
    summary = summarize(run, sampler.rows, record, poses, frames, args, kill)
    summary.update({"keyframes": len(keyframe_seqs), "psnr": psnr_value, "psnr_frames": psnr_frames,
                    "session": sid, "map_while_finishing": probe or None})
    return {"summary": summary, "run": run, "samples": sampler.rows}


async def _map_while_finishing(run: LiveRun, http, sid: str, out: dict) -> None:
    """Once the session reports `finishing`, ask for its map as the web viewer would (spz): how long the answer
    took, its status and size, and whether the session was still finishing when it came."""
    while run.finish_sent is None and run.failure is None:
        await asyncio.sleep(0.05)
    while run.failure is None and run.finished is None:
        if (await http.get(f"/v1/sessions/{sid}")).json().get("status") == "finishing":
            break
        await asyncio.sleep(0.1)
    else:
        out["note"] = "the session finished before a request could be sent"
        return
    began = time.monotonic()
    reply = await http.get(f"/v1/sessions/{sid}/map", params={"format": "spz"})
    out.update({"after_finish_sent_s": round(began - run.finish_sent, 2),
                "latency_s": round(time.monotonic() - began, 3), "http_status": reply.status_code,
                "bytes": len(reply.content),
                "session_status_after": (await http.get(f"/v1/sessions/{sid}")).json().get("status")})


async def _kill_when_running(run: LiveRun, sent: int, stack, http, sid: str, out: dict, min_poses: int = 5) -> None:
    """Once `sent` frames are on the wire and poses are flowing (`min_poses` received), kill the owning worker and
    start a new one at once (what `flashmono serve` does)."""

    def progress() -> tuple[int, int]:
        return sum(f.sent is not None for f in run.frames), sum(f.pose is not None for f in run.frames)

    await kill_when(progress, sent, stack, http, sid, out, min_poses=min_poses, restart=True)


async def _live_psnr(http, sid, frames, poses, keyframe_seqs, intrinsics, every: int, se3_part) -> tuple[float, int]:
    """Mean PSNR of every `every`-th non-keyframe rendered by the service (GET render) from its final pose, as
    captured (`exposure_of` its seq: under the exposure interpolated between its keyframes, as `flashmono run`
    scores)."""
    from client.async_sdk import decode_png
    from worker.eval import non_keyframe_indices, psnr

    k = intrinsics
    mapped = [i in keyframe_seqs or i == len(frames) - 1 for i in range(len(frames))]
    chosen = [i for i in non_keyframe_indices(mapped, every) if i in poses]
    scores = []
    for i in chosen:
        pose = se3_part(poses[i])
        params = {"pose": ",".join(f"{v:.9g}" for v in pose.reshape(-1)), "width": k.width, "height": k.height,
                  "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "exposure_of": i}
        response = await http.get(f"/v1/sessions/{sid}/render", params=params)
        if response.status_code != 200:
            continue
        scores.append(psnr(decode_png(response.content), frames[i].image))
    return (float(np.mean(scores)) if scores else None), len(scores)


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def summarize(run: LiveRun, samples: list[dict], record: dict, poses: dict, frames, args, kill: dict) -> dict:
    logs = run.frames
    acked = [i for i, f in enumerate(logs) if f.acked is not None]
    capture_lat = [1000 * (f.pose - f.capture) for f in logs if f.pose is not None]
    send_lat = [1000 * (f.pose - f.sent) for f in logs if f.pose is not None and f.sent is not None]
    skipped = {i for i, f in enumerate(logs) if f.skipped is not None}
    answered = set(poses) | skipped
    out: dict[str, Any] = {
        "frames": len(logs), "fps": args.fps, "acked": len(acked), "with_pose": sum(f.pose is not None for f in logs),
        "skipped": len(skipped), "result_errors": sum(1 for f in logs if f.error and f.acked is not None),
        "resends": sum(max(0, f.sends - 1) for f in logs), "rewinds": run.rewinds,
        "latency_ms": {q: _pct(capture_lat, q) for q in (50, 95, 99)},
        "latency_from_send_ms": {q: _pct(send_lat, q) for q in (50, 95, 99)},
        "send_span_s": (max(f.sent for f in logs if f.sent) - run.start) if any(f.sent for f in logs) else None,
        "finish_s": (run.finished - run.finish_sent) if run.finished and run.finish_sent else None,
        "total_s": (run.finished or time.monotonic()) - run.start,
        "types": dict(run.types), "failure": run.failure, "status": record.get("status"),
        "acked_lost": len(set(acked) - answered), "duplicate_poses": sum(max(0, f.poses - 1) for f in logs),
        "rss_worker_peak_mib": max((s["worker_rss"] for s in samples), default=None),
        "rss_gateway_peak_mib": max((s["gateway_rss"] for s in samples), default=None),
        "loops": run.types.get("loop_closed", 0),
    }
    for key in ("mapping_lag_keyframes", "mapping_lag_s"):
        values = [s[key] for s in samples if s.get(key) is not None]
        out[f"{key}_max"] = max(values) if values else None
    out["frames_skipped_record"] = record.get("frames_skipped")
    out["latency_max_ms"] = max(capture_lat, default=None)
    out["pose_source_chosen"] = pose_source_verdict(run)
    out["ate_m"] = ate(poses, frames, rgb_only=args.mode == "rgb")
    if kill.get("at"):
        times = sorted(f.pose for f in logs if f.pose is not None)
        before = [t for t in times if t <= kill["at"]]
        after = [t for t in times if t > kill["at"]]
        out["kill"] = {"owner": kill.get("owner"), "at_frame": kill.get("at_frame_sent"),
                       "poses_before": kill.get("poses_before"), "at_s": kill["at"] - run.start,
                       "gap_s": (after[0] - kill["at"]) if after else None,
                       "pose_gap_s": (after[0] - before[-1]) if after and before else None,
                       "phases": kill.get("phases")}
    return out


def pose_source_verdict(run: LiveRun) -> dict[str, Any] | None:
    """Posed modes: the `pose_source_chosen` event as received (source, frames replayed, at which frame) and what
    the verdict cost the frame it came with (its capture -> pose latency: the replay of the judged frames)."""
    chosen = next((m for _, m in run.events if m.get("type") == "pose_source_chosen"), None)
    if chosen is None:
        return None
    seq = chosen.get("seq")
    log = run.frames[int(seq)] if seq is not None and 0 <= int(seq) < len(run.frames) else None
    return {"pose_source": chosen.get("pose_source"), "seq": seq, "frames_replayed": chosen.get("frames_replayed"),
            "latency_ms": 1000 * (log.pose - log.capture) if log is not None and log.pose is not None else None}


def run_offline(source: str, size, max_frames, args, out_dir: Path) -> dict[str, Any]:
    """The same frames through the offline engine (`flashmono run`), scored like the live run."""
    from worker.config import SlamConfig
    from worker.eval import read_tum
    from worker.offline import run_sequence

    start = time.perf_counter()
    if args.preset:
        config = SlamConfig.preset(args.preset, tracking={"max_side": args.tracking_side or 0})
    else:  # what `flashmono run` chooses for these frames
        from client.commands.run import load_config

        config = load_config(argparse.Namespace(use_gt_depth=mode_inputs(args.mode)[0],
                                                use_gt_poses=mode_inputs(args.mode)[1], preset=None, config=None,
                                                finish_budget=None, deterministic=False))
        if args.tracking_side:
            config = config.model_copy(update={"tracking": config.tracking.model_copy(
                update={"max_side": args.tracking_side})})
    with_depth, with_pose = mode_inputs(args.mode)
    metrics = run_sequence(source, out_dir, config, use_gt_depth=with_depth, use_gt_poses=with_pose,
                           max_frames=max_frames, resize=size, eval_every=max(1, args.psnr_every))
    wall = time.perf_counter() - start
    tum = read_tum(out_dir / "trajectory_all.tum")
    frames, _ = load_frames(source, size, max_frames, with_depth=False)
    by_time = {round(float(t), 6): p for t, p in zip(tum.timestamps, tum.poses)}
    poses = {i: by_time[round(f.timestamp, 6)] for i, f in enumerate(frames) if round(f.timestamp, 6) in by_time}
    return {"ate_m": ate(poses, frames, rgb_only=args.mode == "rgb"), "psnr": metrics.get("psnr"),
            "fps": metrics.get("fps"), "fps_streaming": metrics.get("fps_streaming"), "wall_s": wall,
            "keyframes": metrics.get("num_keyframes"), "loops": metrics.get("loops")}


# ------------------------------------------------------------------------------------------------ reporting
def plot(result: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run: LiveRun = result["run"]
    samples = result["samples"]
    t0 = run.start
    fig, axes = plt.subplots(3, 1, figsize=(9, 9))
    pts = [(i, 1000 * (f.pose - f.capture)) for i, f in enumerate(run.frames) if f.pose is not None]
    if pts:
        axes[0].plot(*zip(*pts), ".", ms=3, label="capture -> pose")
    sk = [(i, 1000 * (f.skipped - f.capture)) for i, f in enumerate(run.frames) if f.skipped is not None]
    if sk:
        axes[0].plot(*zip(*sk), "x", ms=3, label="capture -> skipped")
    axes[0].axhline(100, color="red", lw=0.8, ls="--", label="100 ms target")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("latency (ms)")
    axes[0].set_xlabel("frame (seq)")
    axes[0].legend(fontsize=8)
    ts = [s["t"] - t0 for s in samples]
    axes[1].plot(ts, [s["worker_rss"] for s in samples], label="worker")
    axes[1].plot(ts, [s["gateway_rss"] for s in samples], label="gateway")
    axes[1].set_ylabel("RSS (MiB)")
    axes[1].set_xlabel("seconds since the first frame's capture")
    axes[1].legend(fontsize=8)
    sent = [(f.sent - t0, i) for i, f in enumerate(run.frames) if f.sent is not None]
    if sent:
        axes[2].plot(*zip(*sorted(sent)), label="frames sent (last send)")
    posed = sorted(f.pose - t0 for f in run.frames if f.pose is not None)
    if posed:
        axes[2].plot(posed, range(1, len(posed) + 1), label="poses received")
    lag = [(s["t"] - t0, s["mapping_lag_keyframes"]) for s in samples if s.get("mapping_lag_keyframes") is not None]
    if lag:
        twin = axes[2].twinx()
        twin.plot(*zip(*lag), color="grey", ls=":", label="mapping lag (keyframes)")
        twin.set_ylabel("mapping lag (keyframes)")
    if result["summary"].get("kill"):
        for ax in axes[1:]:
            ax.axvline(result["summary"]["kill"]["at_s"], color="black", lw=0.8, ls="--")
    axes[2].set_ylabel("frames")
    axes[2].set_xlabel("seconds since the first frame's capture")
    axes[2].legend(fontsize=8, loc="upper left")
    fig.suptitle("\n".join(textwrap.wrap(title, 100)), fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _ms(v) -> str:
    return "-" if v is None else f"{v:,.0f}"


def row(label: str, s: dict, offline: dict | None, load: str) -> str:
    lat = s["latency_ms"]
    ate_cm = "-" if s["ate_m"] is None else f"{100 * s['ate_m']:.2f}"
    psnr = "-" if s["psnr"] is None else f"{s['psnr']:.2f}"
    off = ("-", "-") if offline is None else (
        "-" if offline["ate_m"] is None else f"{100 * offline['ate_m']:.2f}",
        "-" if offline["psnr"] is None else f"{offline['psnr']:.2f}")
    lag = "-" if s["mapping_lag_keyframes_max"] is None else (
        f"{s['mapping_lag_keyframes_max']} kf / {s['mapping_lag_s_max']:.1f} s")
    finish = "-" if s["finish_s"] is None else f"{s['finish_s']:.1f}"
    return (f"| {label} | {s['frames']} | {s['acked']} | {s['with_pose']} | {s['skipped']} | {s['resends']} | "
            f"{_ms(lat[50])} / {_ms(lat[95])} / {_ms(lat[99])} | {finish} | {lag} | "
            f"{s['rss_worker_peak_mib']:.0f} | {ate_cm} / {off[0]} | {psnr} / {off[1]} | {load} |")


HEADER = ("| case | frames | acked | with pose | skipped | re-sent | latency p50 / p95 / p99 (ms) | finish (s) | "
          "max mapping lag | worker RSS peak (MiB) | ATE live / offline (cm) | PSNR live / offline (dB) | load |\n"
          "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")


def live_values(summary: dict[str, Any]) -> dict[str, Any]:
    """The scoreboard's figures of a live run (bench.out_of_box writes the same keys)."""
    return {"posed_share": summary["with_pose"] / max(1, summary["frames"]), "frames": summary["frames"],
            "latency_p50_ms": summary["latency_ms"][50], "latency_p95_ms": summary["latency_ms"][95],
            "finish_s": summary["finish_s"], "ate_m": summary["ate_m"], "psnr_db": summary["psnr"],
            "rss_worker_peak_mib": summary["rss_worker_peak_mib"], "acked_lost": summary["acked_lost"]}


def offline_values(offline: dict[str, Any]) -> dict[str, Any]:
    """The scoreboard's figures of the offline run of the same frames."""
    return {"ate_m": offline.get("ate_m"), "psnr_db": offline.get("psnr"), "fps": offline.get("fps"),
            "wall_s": offline.get("wall_s")}


def live_case(args: argparse.Namespace) -> dict[str, Any]:
    """The case a run measures; options off their defaults name a variant (its own row, not the default's)."""
    variant = [f"{args.fps:g} fps" if args.fps != 30.0 else "", f"{args.frames} frames" if args.frames else "",
               f"preset {args.preset}" if args.preset else "", "every frame" if args.every_frame else "",
               f"tracked at {args.tracking_side} px" if args.tracking_side else "",
               f"worker killed at {args.kill_at:.0%}" if args.kill_at is not None else ""]
    case = {"sequence": Path(args.source).name, "mode": args.mode, "size": args.size}
    if any(variant):
        case["variant"] = ", ".join(v for v in variant if v)
    return case


def write_records(recorder: Recorder, case: dict[str, Any], summary: dict[str, Any],
                  offline: dict[str, Any] | None) -> None:
    recorder.write({"area": "live", **case}, live_values(summary))
    if offline is not None:
        recorder.write({"area": "offline", **case}, offline_values(offline))


def main(argv: list[str]) -> int:
    from service.launcher import LocalStack

    parser = argparse.ArgumentParser(prog="python -m bench live")
    parser.add_argument("--source", default=str(MINI), help="a sequence with ground truth (default: icl_mini)")
    parser.add_argument("--mode", choices=MODES, default="rgbd",
                        help="rgbd: send depth, no poses; rgb: images only; posed-rgb / posed-rgbd: the sequence's "
                        "poses sent as the device's (the session's pose_mode auto judges and seeds from them)")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--tracking-side", type=int, default=0,
                        help="the session's tracking resolution (long side; 0: the frames' size)")
    parser.add_argument("--fps", type=float, default=30.0, help="the client's frame rate")
    parser.add_argument("--frames", type=int, default=None, help="at most this many frames")
    parser.add_argument("--preset", default=None,
                        help="name a preset (default: none, as openapi.yaml documents a session: the worker chooses)")
    parser.add_argument("--every-frame", action="store_true",
                        help="a session without live skipping (skip_frames false): every frame tracked however late")
    parser.add_argument("--kill-at", type=float, default=None,
                        help="SIGKILL the owning worker when this fraction of the frames is sent")
    parser.add_argument("--psnr-every", type=int, default=5, help="render every N-th non-keyframe (0: no PSNR)")
    parser.add_argument("--no-offline", action="store_true", help="skip the offline run of the same frames")
    parser.add_argument("--map-while-finishing", action="store_true",
                        help="request the map (spz) once the session is finishing, and report how long it took")
    parser.add_argument("--worker-nice", type=int, default=10, help="as `flashmono serve` (default 10)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (a second one can take over at once)")
    parser.add_argument("--timeout-s", type=float, default=1800.0)
    parser.add_argument("--plot", default=None, help="PNG path (default: none)")
    parser.add_argument("--json", default=None, help="write the summary (and per-frame times) here")
    parser.add_argument("--label", default=None)
    parser.add_argument("--write-results", action="store_true",
                        help="write the result records (bench/results/live/); the row goes to the journal's inbox")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    with_depth, with_pose = mode_inputs(args.mode)
    frames, intrinsics = load_frames(args.source, size, args.frames, with_depth=with_depth, with_pose=with_pose)
    messages = encode(frames, with_depth=with_depth, with_pose=with_pose)
    label = args.label or (f"{Path(args.source).name} {args.mode} {args.size} @ {args.fps:g} fps"
                           + (f", tracked at {args.tracking_side} px" if args.tracking_side else "")
                           + (f", worker killed at {args.kill_at:.0%}" if args.kill_at is not None else ""))
    recorder = Recorder("live", argv)
    load_before = os.getloadavg()
    print(f"{label}: {len(frames)} frames, {sum(map(len, messages)) / len(messages) / 1024:.1f} KiB a message, "
          f"load {load_before[0]:.2f}", flush=True)
    env = {"FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=args.workers, worker_env=env, worker_nice=args.worker_nice) as stack:
        result = asyncio.run(stream_case(stack, frames, intrinsics, messages, args))
    summary = result["summary"]
    load_after = os.getloadavg()
    load = f"{load_before[0]:.1f} -> {load_after[0]:.1f}"
    offline = None
    if not args.no_offline:
        with tempfile.TemporaryDirectory(prefix="bench-live-offline-") as out:
            offline = run_offline(args.source, size, args.frames, args, Path(out))
        summary["offline"] = offline
    summary["load"] = load
    print(json.dumps(summary, indent=1, default=str))
    print(HEADER)
    print(row(label, summary, offline, load))
    if args.plot:
        plot(result, Path(args.plot), f"{label} (load {load})")
        print(f"plot: {args.plot}")
    if args.json:
        per_frame = [{"capture": f.capture - result["run"].start, "sent": f.sent and f.sent - result["run"].start,
                      "pose": f.pose and f.pose - result["run"].start,
                      "skipped": f.skipped and f.skipped - result["run"].start, "sends": f.sends}
                     for f in result["run"].frames]
        Path(args.json).write_text(json.dumps({"summary": summary, "frames": per_frame,
                                               "samples": result["samples"]}, default=str))
    if args.write_results:
        RESULTS.write_text(RESULTS.read_text().rstrip("\n") + "\n" + row(label, summary, offline, load) + "\n")
        write_records(recorder, live_case(args), summary, offline)
    ok = summary["acked_lost"] == 0 and summary["failure"] is None and summary["duplicate_poses"] == 0
    return 0 if ok else 1
