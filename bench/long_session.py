"""Long sessions through the offline engine (issue 24 points 3 and 4): does the cost stay flat as a session grows?

Streams (worker.slam.SlamSystem directly, the engine `flashmono run` drives) one of:
- `synthetic`: one lap around a procedural room (`synthetic://seed=3?frames=LAP`, exact depth and poses; 300
  frames = 10 s a lap by default) played forward and back up to N frames: the room circled again and again;
- a `synthetic://seed=3?frames=N` URI as it is: one slow lap over all N frames (the issue's `flashmono run` case);
- `icl`: the ICL living-room sequence (the full 211 frames under /work/shared when present, else tests/data/icl_mini)
  played forward and back, again and again, up to N frames (re-indexed, timestamps at 30 frames/s): the same
  places over and over, so a map that follows the scene stops growing after the first sweep;
- any other path `worker.data.open_source` reads, played forward and back the same way.

Records per frame: the wall time of `push` (what a caller waits), the tracking time inside it, the loop-detection
time of each keyframe, the keyframe count, the map size (surfels, sampled) and the process RSS, against the frame
count; then `finish` time, the final ATE (SE(3)-aligned with depth, Sim(3) for RGB only) and peak RSS. Writes a
PNG plot and a CSV of the per-frame rows, and prints a table by frame-count buckets. With depth, Open3D's RGB-D
odometry (frame to frame, bench/rgbd_odometry.py) is timed on the first and the last `--open3d-window` frames as
the CPU peer (skipped with a note when `open3d` is not installed).

`--snapshot-every N` measures the worker's snapshot every N frames: the bytes an incremental snapshot write
carries (`SlamSystem.begin_snapshot(stored_chunks)`: the snapshot, the trajectory chunks and the arrays not stored
yet: what the worker writes to Redis) against a self-contained one (what each write carried before: everything),
and the time to restore from it. `--kill-at F` drops the engine at frame F and takes over as a new worker would
(restore the snapshot taken `--kill-replay` frames earlier, replay those frames, go on), reporting the recovery time.

Long runs checkpoint: `--checkpoint-dir D` saves the engine snapshot (SlamSystem.snapshot) and the rows every
`--checkpoint-every` frames; running the same command again resumes from the newest checkpoint.

`python -m bench long_session [--source synthetic|icl|PATH] [--frames N] [--mode rgbd|rgb] [--size 320x240]
[--plot PATH] [--csv PATH] [--checkpoint-dir D] [--checkpoint-every 1000] [--no-finish] [--write-results]`
(defaults: synthetic, 600 frames: a few minutes on 2 cores; the issue's target length is --frames 18000).
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import os
import resource
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bench.record import JOURNAL_INBOX, Recorder

ROOT = Path(__file__).resolve().parent.parent
SHARED_ICL = Path("/work/shared/data/icl_livingroom1_micro")
MINI = ROOT / "tests" / "data" / "icl_mini"
RESULTS = JOURNAL_INBOX  # bench/RESULTS.md is generated (python -m bench scoreboard): narrative goes to the journal
MAP_SAMPLE_EVERY = 25  # frames between map-size samples (the count takes the backend's lock)
FIELDS = ("frame", "push_ms", "tracking_ms", "loop_detection_ms", "loop_detections", "is_keyframe", "keyframes",
          "surfels", "rss_mib", "wall_s")


# ---------------------------------------------------------------------------------------------------- frames
def ping_pong(count: int, total: int) -> Iterator[int]:
    """0, 1, ..., count-1, count-2, ..., 0, 1, ... (`total` indices): a sequence played forward and back."""
    if count < 2:
        raise ValueError("a ping-pong needs at least two frames")
    period = 2 * (count - 1)
    for k in range(total):
        phase = k % period
        yield phase if phase < count else period - phase


def long_stream(source: str, frames: int, size: tuple[int, int], with_depth: bool, lap: int = 300):
    """(frame iterator, intrinsics, description) of `frames` frames of `source` (see the module docstring)."""
    from worker.data import open_source
    from worker.data.frame import Frame

    if source.startswith("synthetic://"):  # streamed as it is: one lap of the room over all its frames
        src = open_source(source, use_gt_depth=with_depth, use_gt_poses=False)
        return iter(src), src.intrinsics, source
    if source == "synthetic":  # one lap of `lap` frames, played forward and back
        path = f"synthetic://seed=3?frames={lap}&width={size[0]}&height={size[1]}"
        src = open_source(path, use_gt_depth=True, use_gt_poses=False)
    else:
        path = (SHARED_ICL if SHARED_ICL.is_dir() else MINI) if source == "icl" else Path(source)
        src = open_source(str(path), resize=size, use_gt_depth=True, use_gt_poses=False)
    base = list(src)
    fps = 30.0

    def frames_iter() -> Iterator[Frame]:
        for k, i in enumerate(ping_pong(len(base), frames)):
            f = base[i]
            yield Frame(index=k, timestamp=k / fps, image=f.image, intrinsics=f.intrinsics,
                        depth=f.depth if with_depth else None, gt_pose=f.gt_pose)

    sweeps = frames / max(1, len(base) - 1)
    name = path if isinstance(path, str) else path.name
    return frames_iter(), src.intrinsics, f"{name} ({len(base)} frames) forward and back, {sweeps:.1f} sweeps"


def rss_mib() -> float:
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20
    except ImportError:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


# ------------------------------------------------------------------------------------------------- the run
class StageClock:
    """Per-frame deltas of the engine's stage totals (SlamSystem.timings), tolerant of engines without them."""

    def __init__(self, system) -> None:
        self.system = system
        self.last = self._totals()

    def _totals(self) -> dict[str, float]:
        timings = getattr(self.system, "timings", None)
        seconds = dict(getattr(timings, "seconds", {}) or {})
        counts = {f"{k}#": float(v) for k, v in (getattr(timings, "counts", {}) or {}).items()}
        return seconds | counts

    def delta(self) -> dict[str, float]:
        """Seconds per stage since the last call, and events as `stage#` (a stage may run in another thread: its
        time is attributed to the frame during which it ended)."""
        now = self._totals()
        out = {k: v - self.last.get(k, 0.0) for k, v in now.items()}
        self.last = now
        return out


def run(args, out_rows: list[dict], checkpoint: Path | None) -> dict[str, Any]:
    import torch

    from worker.config import SlamConfig
    from worker.slam import SlamSystem

    size = tuple(int(v) for v in args.size.split("x"))
    with_depth = args.mode == "rgbd"
    frames, intrinsics, description = long_stream(args.source, args.frames, size, with_depth, args.lap)
    config = SlamConfig.preset(args.preset)
    config = config.model_copy(update={"input": config.input.model_copy(update={"use_depth": with_depth})})
    start_at = 0
    if checkpoint is not None and (checkpoint / "engine.msgpack").exists():
        system = SlamSystem.restore((checkpoint / "engine.msgpack").read_bytes())
        state = json.loads((checkpoint / "state.json").read_text())
        out_rows.extend(state["rows"])
        start_at = state["next_frame"]
        gt = {int(k): np.asarray(v) for k, v in state["gt"].items()}
        print(f"resumed at frame {start_at} from {checkpoint}", flush=True)
    else:
        system = SlamSystem(config, intrinsics=intrinsics)
        gt = {}
    torch.set_num_threads(args.threads)
    clock = StageClock(system)
    snapshots: list[dict[str, Any]] = []
    stored: dict[str, Any] = {}  # the trajectory chunks and arrays "stored" so far (measure_snapshot)
    kill_snapshot, since_snapshot, kill = None, None, None
    window = args.open3d_window
    first_frames, last_frames = [], collections.deque(maxlen=window)
    surfels = out_rows[-1]["surfels"] if out_rows else 0
    t0 = time.perf_counter() - (out_rows[-1]["wall_s"] if out_rows else 0.0)
    for frame in frames:
        k = frame.index
        if k < start_at:
            continue
        if with_depth and window:
            (first_frames if len(first_frames) < window else last_frames).append(frame)
        if frame.gt_pose is not None and k % args.gt_every == 0:
            gt[k] = np.asarray(frame.gt_pose, np.float64)
        start = time.perf_counter()
        result = system.push(frame)
        push_ms = 1000 * (time.perf_counter() - start)
        d = clock.delta()
        if k % MAP_SAMPLE_EVERY == 0 or result.is_keyframe and k % 5 == 0:
            surfels = system.num_gaussians
        out_rows.append({
            "frame": k, "push_ms": push_ms,
            "tracking_ms": 1000 * (d.get("frontend_tracking", 0.0) + d.get("frontend_inference", 0.0)),
            "loop_detection_ms": 1000 * d.get("loop_detection", 0.0),
            "loop_detections": int(d.get("loop_detection#", 0)), "is_keyframe": int(result.is_keyframe),
            "keyframes": int(system.counters.get("keyframes", 0)), "surfels": surfels,
            "rss_mib": rss_mib() if k % 10 == 0 else out_rows[-1]["rss_mib"] if out_rows else rss_mib(),
            "wall_s": time.perf_counter() - t0})
        if k % 200 == 0:
            r = out_rows[-1]
            print(f"frame {k}: push {r['push_ms']:.0f} ms, tracking {r['tracking_ms']:.0f} ms, {r['keyframes']} "
                  f"keyframes, {r['surfels']} surfels, RSS {r['rss_mib']:.0f} MiB, {r['wall_s']:.0f} s, load "
                  f"{os.getloadavg()[0]:.1f}", flush=True)
        if checkpoint is not None and args.checkpoint_every and k and k % args.checkpoint_every == 0:
            save_checkpoint(checkpoint, system, out_rows, k + 1, gt)
        if args.snapshot_every and (k + 1) % args.snapshot_every == 0:
            snapshots.append(measure_snapshot(system, stored, k + 1))
            print(f"snapshot at frame {k + 1}: {json.dumps(snapshots[-1])}", flush=True)
        if args.kill_at is not None:
            if k + 1 == args.kill_at - args.kill_replay:  # the worker's newest stored snapshot before the kill
                kill_snapshot = system.begin_snapshot(stored_chunks={})
                kill_snapshot.result()
                since_snapshot = []
            elif since_snapshot is not None:
                since_snapshot.append(frame)
            if k + 1 == args.kill_at:
                system, kill = kill_and_take_over(system, kill_snapshot, since_snapshot)
                since_snapshot = None
                clock = StageClock(system)
                print(f"killed at frame {k + 1}: {json.dumps(kill)}", flush=True)
    streaming_s = time.perf_counter() - t0
    finish_s = None
    if not args.no_finish:
        start = time.perf_counter()
        system.finish()
        finish_s = time.perf_counter() - start
    summary = {"description": description, "frames": len(out_rows), "streaming_s": streaming_s,
               "finish_s": finish_s, "surfels_final": system.num_gaussians,
               "keyframes": int(system.counters.get("keyframes", 0)),
               "loops": int(system.counters.get("loops", 0)),
               "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
               "ate_m": final_ate(system, gt, rgb_only=not with_depth), "snapshots": snapshots, "kill": kill}
    system.close()
    if with_depth and window:
        summary["open3d"] = open3d_peer(first_frames, list(last_frames), intrinsics)
    return summary


def save_checkpoint(directory: Path, system, rows: list[dict], next_frame: int, gt: dict) -> None:
    """Snapshot and rows, written to temporary names first so a kill mid-write leaves the previous checkpoint."""
    directory.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    data = system.snapshot()
    (directory / "engine.msgpack.tmp").write_bytes(data)
    (directory / "state.json.tmp").write_text(json.dumps({"rows": rows, "next_frame": next_frame,
                                                          "gt": {k: v.tolist() for k, v in gt.items()}}))
    os.replace(directory / "engine.msgpack.tmp", directory / "engine.msgpack")
    os.replace(directory / "state.json.tmp", directory / "state.json")
    print(f"checkpoint at frame {next_frame}: {len(data) / 2**20:.1f} MiB in {time.perf_counter() - start:.1f} s",
          flush=True)


def measure_snapshot(system, stored: dict[str, Any], frames: int) -> dict[str, Any]:
    """One incremental snapshot as the worker writes it (`stored`: the trajectory chunks and arrays written
    before, updated here), beside the self-contained size (what every write carried before), the sizes of the
    parts kept outside (per stage: their arrays), and the time to restore from it."""
    from protocol.codec import unpack
    from worker.slam import SlamSystem

    chunks: dict[int, tuple[int, bytes]] = stored.setdefault("chunks", {})
    arrays: dict[str, bytes] = stored.setdefault("arrays", {})
    start = time.perf_counter()
    future = system.begin_snapshot(stored_chunks={i: v for i, (v, _) in chunks.items()})
    blob = future.result()
    ready_s = time.perf_counter() - start
    write = future.chunks
    chunks.update({i: (write.versions()[i], raw) for i, raw in write.new.items()})
    new_arrays = {d: raw for d, raw in write.arrays.items() if d not in arrays}
    arrays.clear()
    arrays.update(write.arrays)  # what the store keeps: the arrays this snapshot names
    parts = unpack(blob)
    start = time.perf_counter()
    restored = SlamSystem.restore(blob, {**{i: raw for i, (_, raw) in chunks.items()}, **arrays})
    restore_s = time.perf_counter() - start
    assert len(restored.trajectory("all")) == len(system.trajectory("all"))
    restored.close()
    return {"frame": frames, "keyframes": int(system.counters.get("keyframes", 0)),
            "write_bytes": len(blob) + sum(map(len, write.new.values())) + sum(map(len, new_arrays.values())),
            "self_contained_bytes": len(blob) + sum(len(raw) for _, raw in chunks.values())
            + sum(map(len, arrays.values())),
            "snapshot_bytes": len(blob), "trajectory_chunk_bytes": sum(len(raw) for _, raw in chunks.values()),
            "arrays": len(arrays), "arrays_bytes": sum(map(len, arrays.values())),
            "new_arrays_bytes": sum(map(len, new_arrays.values())), "chunks_written": len(write.new),
            "inline_tracking_bytes": len(parts["tracking"]), "inline_map_bytes": len(parts["map"] or b""),
            "inline_loop_bytes": len(parts["loop"]), "ready_s": round(ready_s, 3), "restore_s": round(restore_s, 3)}


def kill_and_take_over(system, snapshot, replay: list) -> tuple[Any, dict[str, Any]]:
    """What a new owner does after the owner died: restore the newest snapshot (with its parts), replay the frames
    answered since, and go on; returns the new system and the times, with the replayed poses' largest difference
    from the dead system's (the same frames tracked again)."""
    from worker.slam import SlamSystem

    before = {int(i): p for i, _, p in system.trajectory("all")}
    system.close()
    write = snapshot.chunks
    start = time.perf_counter()
    restored = SlamSystem.restore(snapshot.result(), {**write.arrays, **write.new})
    restore_s = time.perf_counter() - start
    start = time.perf_counter()
    for frame in replay:
        restored.push(frame)
    replay_s = time.perf_counter() - start
    after = {int(i): p for i, _, p in restored.trajectory("all")}
    moved = max((float(np.abs(after[i][:3, 3] - before[i][:3, 3]).max()) for i in after if i in before), default=0.0)
    return restored, {"restore_s": round(restore_s, 3), "replayed_frames": len(replay), "replay_s": round(replay_s, 3),
                      "recovery_s": round(restore_s + replay_s, 3), "frames_kept": len(after) == len(before),
                      "max_position_difference_m": moved, "snapshot_bytes": len(snapshot.result()),
                      "parts_bytes": sum(map(len, write.arrays.values())) + sum(map(len, write.new.values()))}


def final_ate(system, gt: dict[int, np.ndarray], rgb_only: bool) -> float | None:
    from worker.eval import absolute_trajectory_error

    poses = {int(i): p for i, _, p in system.trajectory("all")}
    keys = [k for k in sorted(gt) if k in poses]
    if len(keys) < 3:
        return None
    est = np.stack([poses[k] for k in keys])
    ref = np.stack([gt[k] for k in keys])
    return float(absolute_trajectory_error(est, ref, "sim3" if rgb_only else "se3").rmse)


def open3d_peer(first: list, last: list, intrinsics) -> dict[str, Any]:
    """Open3D's frame-to-frame RGB-D odometry, ms per frame on the first and the last frames of the stream."""
    from bench.rgbd_odometry import run_open3d

    out: dict[str, Any] = {}
    for name, frames in (("first", first), ("last", last)):
        if len(frames) < 2:
            continue
        try:
            _, seconds, lost = run_open3d(frames, intrinsics)
        except ImportError as err:
            return {"note": f"open3d not installed ({err})"}
        out[name] = {"frames": len(frames), "ms_per_frame": 1000 * seconds, "lost": lost,
                     "from_frame": frames[0].index}
    return out


# ------------------------------------------------------------------------------------------------ reporting
def bucket_table(rows: list[dict], buckets: int = 6) -> str:
    lines = ["| frames | push ms (median) | tracking ms (median / p95) | loop detection ms per keyframe | "
             "keyframes | surfels | RSS MiB |", "|---|---:|---:|---:|---:|---:|---:|"]
    edges = np.linspace(0, len(rows), buckets + 1).astype(int)
    for a, b in zip(edges[:-1], edges[1:]):
        part = rows[a:b]
        if not part:
            continue
        track = [r["tracking_ms"] for r in part]
        events = sum(r.get("loop_detections", r["is_keyframe"]) for r in part)
        loop_ms = sum(r["loop_detection_ms"] for r in part) / events if events else 0.0
        lines.append(f"| {part[0]['frame']}-{part[-1]['frame']} | {np.median([r['push_ms'] for r in part]):.0f} | "
                     f"{np.median(track):.1f} / {np.percentile(track, 95):.1f} | "
                     f"{loop_ms:.0f} ({events} kf) | {part[-1]['keyframes']} | "
                     f"{part[-1]['surfels']:,} | {max(r['rss_mib'] for r in part):.0f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = np.array([r["frame"] for r in rows])
    fig, axes = plt.subplots(4, 1, figsize=(9, 11), sharex=True)

    def rolling(values: np.ndarray, n: int = 31) -> np.ndarray:
        pad = np.pad(values, (n // 2, n // 2), mode="edge")
        return np.array([np.median(pad[i:i + n]) for i in range(len(values))])

    push = np.array([r["push_ms"] for r in rows])
    track = np.array([r["tracking_ms"] for r in rows])
    axes[0].plot(frames, push, ",", color="tab:blue", alpha=0.4)
    axes[0].plot(frames, rolling(push), color="tab:blue", label="push (median of 31)")
    axes[0].plot(frames, rolling(track), color="tab:orange", label="tracking inside push (median of 31)")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("ms per frame")
    axes[0].legend(fontsize=8)
    kf = [(r["frame"], r["loop_detection_ms"] / r.get("loop_detections", 1)) for r in rows
          if r.get("loop_detections", r["is_keyframe"])]
    if kf:
        axes[1].plot(*zip(*kf), ".", ms=3)
    axes[1].set_ylabel("loop detection ms / keyframe")
    axes[2].plot(frames, [r["surfels"] for r in rows], color="tab:green", label="surfels")
    axes[2].set_ylabel("surfels")
    twin = axes[2].twinx()
    twin.plot(frames, [r["keyframes"] for r in rows], color="tab:red", label="keyframes")
    twin.set_ylabel("keyframes")
    axes[3].plot(frames, [r["rss_mib"] for r in rows], color="tab:purple")
    axes[3].axhline(2048, color="red", lw=0.8, ls="--")
    axes[3].set_ylabel("process RSS (MiB)")
    axes[3].set_xlabel("frame")
    fig.suptitle("\n".join(textwrap.wrap(title, 100)), fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def record_case(args: argparse.Namespace) -> dict:
    """The run's record case (area "long_session"), named as the scoreboard's rows are."""
    name = {"icl": "ICL", "synthetic": "synthetic room"}.get(args.source, args.source if
                                                            args.source.startswith("synthetic://") else
                                                            Path(args.source).name)
    sequence = name if args.source.startswith("synthetic://") else f"{name} forward and back"
    case = {"area": "long_session", "sequence": f"{sequence}, {args.frames:,} frames", "mode": args.mode}
    settings = ([] if args.size == "320x240" else [args.size]) + (
        [] if args.preset == "rgbd" else [f"preset {args.preset}"]) + (
        [] if args.kill_at is None else [f"killed at {args.kill_at}"]) + (["no finish"] if args.no_finish else [])
    return {**case, "variant": ", ".join(settings)} if settings else case


def record_values(summary: dict, rows: list[dict], buckets: int = 6) -> dict:
    """The scoreboard's figures: tracking per frame at the end (median of the last sixth) and at the start, the
    peak RSS, `finish`, ATE, keyframes."""
    part = max(1, len(rows) // buckets)
    tracking = [r["tracking_ms"] for r in rows]
    values = {"tracking_ms": round(float(np.median(tracking[-part:])), 2) if rows else None,
              "tracking_start_ms": round(float(np.median(tracking[:part])), 2) if rows else None,
              "rss_peak_mib": round(summary["peak_rss_mib"]),
              "finish_s": None if summary["finish_s"] is None else round(summary["finish_s"], 2),
              "ate_m": None if summary["ate_m"] is None else round(summary["ate_m"], 5),
              "keyframes": summary["keyframes"], "loops": summary["loops"], "frames": summary["frames"],
              "streaming_s": round(summary["streaming_s"], 2), "surfels": summary["surfels_final"]}
    return values


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench long_session")
    parser.add_argument("--source", default="synthetic", help="synthetic, icl, or a sequence path")
    parser.add_argument("--frames", type=int, default=600, help="stream length (the issue's target: 18000)")
    parser.add_argument("--lap", type=int, default=300, help="synthetic: frames of one lap of the room")
    parser.add_argument("--mode", choices=("rgbd", "rgb"), default="rgbd")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--preset", default="rgbd")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--gt-every", type=int, default=1, help="keep every N-th ground-truth pose for the ATE")
    parser.add_argument("--open3d-window", type=int, default=150, help="frames timed for the Open3D peer (0: off)")
    parser.add_argument("--checkpoint-dir", default=None)
    parser.add_argument("--checkpoint-every", type=int, default=1000)
    parser.add_argument("--no-finish", action="store_true", help="skip finish() (the final refinement)")
    parser.add_argument("--kill-at", type=int, default=None,
                        help="at this frame, drop the engine and take over as a new worker would: restore the "
                        "snapshot taken --kill-replay frames earlier, replay those frames, go on")
    parser.add_argument("--kill-replay", type=int, default=30, help="frames between that snapshot and the kill")
    parser.add_argument("--snapshot-every", type=int, default=0,
                        help="measure a chunked snapshot (bytes written, restore time) every N frames (0: off)")
    parser.add_argument("--plot", default=None)
    parser.add_argument("--csv", default=None)
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args(argv)
    recorder = Recorder("long_session", argv)
    load_before = os.getloadavg()
    rows: list[dict] = []
    checkpoint = Path(args.checkpoint_dir) if args.checkpoint_dir else None
    summary = run(args, rows, checkpoint)
    summary["load"] = f"{load_before[0]:.1f} -> {os.getloadavg()[0]:.1f}"
    table = bucket_table(rows)
    print(json.dumps(summary, indent=1))
    print(table)
    title = f"{summary['description']}, {args.mode}, {args.size} (load {summary['load']})"
    if args.plot:
        plot(rows, Path(args.plot), title)
        print(f"plot: {args.plot}")
    if args.csv:
        with open(args.csv, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=FIELDS)
            writer.writeheader()
            writer.writerows(rows)
    recorder.write(record_case(args), record_values(summary, rows))
    if args.write_results:
        RESULTS.write_text(RESULTS.read_text().rstrip("\n") + f"\n\n{title}: {json.dumps(summary)}\n\n{table}\n")
    return 0
