"""Every input mode a real recorded sequence supports, side by side: RGB only, RGB-D, posed RGB-D and posed RGB
(the `flashmono run` settings: preset rgbd, the final refinement unbounded), on any dataset folder the readers accept
(TUM RGB-D, KITTI odometry, ICL/Open3D, ScanNet, Replica). Issues 20 and 21 ask for these figures on real footage.

Per sequence it prints the motion (frames, path length, rotation per frame), then per mode ATE (Sim(3)-aligned, also
as a share of the path length, the driving figure), PSNR / depth L1 on the held-out frames, frames/s, and what tracking
reported (frames with `tracking_lost` / `relocalized` / input events, read from every frame's result, and the frames
from each loss to its relocalisation). The RGB-only
row also runs the visual odometry alone (as bench/visual_odometry.py does): frames tracked, where it lost and came
back, and its own ATE, since the full system's trajectory hides a frame that stood still while the image moved.

    python -m bench real_sequences --source DIR [--source DIR ...]
                                   [--modes rgb,rgbd,posed_rgbd,posed_rgb,posed_rgbd_fixed] [--width 320]
                                   [--max-frames N] [--stride S] [--out DIR] [--no-vo]

Modes the data cannot support (depth or poses missing) are skipped. Sources measured so far and their licences:
bench/journal/24-real-sequences-issues-20-and-21-python-m-bench-real-sequence.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bench.record import Recorder

MODES = {"rgb": (False, False), "rgbd": (True, False), "posed_rgbd": (True, True), "posed_rgb": (False, True),
         "posed_rgbd_fixed": (True, True)}
# modes that differ from another only in their settings (`posed_rgbd_fixed`: the device poses kept as they are)
MODE_CONFIG = {"posed_rgbd_fixed": {"input": {"pose_mode": "fixed"}}}
EVENT_TYPES = ("tracking_lost", "relocalized", "initialized", "device_pose_jump", "odometry_slip",
               "depth_misregistered")


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the relative rotation between two camera-to-world poses, degrees."""
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def motion_summary(poses: np.ndarray) -> dict[str, float]:
    """Path length and per-frame steps of a ground-truth trajectory [N, 4, 4]."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turns = np.array([rotation_deg(poses[i], poses[i + 1]) for i in range(len(poses) - 1)])
    return {"path_m": float(steps.sum()), "step_median_m": float(np.median(steps)), "step_max_m": float(steps.max()),
            "turn_median_deg": float(np.median(turns)), "turn_p95_deg": float(np.percentile(turns, 95)),
            "turn_max_deg": float(turns.max()), "turn_total_deg": float(turns.sum()),
            "heading_change_deg": rotation_deg(poses[0], poses[-1])}


def resized(width: int, height: int, target_width: int) -> tuple[int, int]:
    """The frame size `target_width` wide with the source's aspect ratio (height rounded)."""
    return target_width, max(1, round(height * target_width / width))


@contextlib.contextmanager
def frame_events() -> Iterator[list[tuple[int, str]]]:
    """Collect, while the block runs, (frame position, event type) of every event in the SlamSystem's frame results
    (the offline run keeps only metrics; its per-frame results are read here by wrapping SlamSystem.push)."""
    from worker.slam import SlamSystem

    seen: list[tuple[int, str]] = []
    push = SlamSystem.push
    position = iter(range(1 << 62))

    def recording_push(self, frame):
        result = push(self, frame)
        at = next(position)
        seen.extend((at, kind) for kind in dict.fromkeys(event.TYPE for event in result.events))
        return result

    SlamSystem.push = recording_push
    try:
        yield seen
    finally:
        SlamSystem.push = push


def lost_spans(events: list[tuple[int, str]], frames: int) -> list[tuple[int, int]]:
    """(first, last) frame positions of each stretch from a `tracking_lost` to the frame before the next
    `relocalized` (or the last frame): the frames tracking did not place (their pose is held, or the device's)."""
    spans, start = [], None
    for at, kind in sorted(events, key=lambda event: event[0]):  # stable: a frame's events keep their order
        if kind == "tracking_lost" and start is None:
            start = at
        elif kind == "relocalized" and start is not None:
            if at > start:  # a frame lost and relocalised at once (seeded: restarted at the device's pose) held none
                spans.append((start, at - 1))
            start = None
    if start is not None:
        spans.append((start, frames - 1))
    return spans


def run_mode(source: Path, mode: str, size: tuple[int, int], max_frames: int | None, stride: int,
             out: Path) -> dict:
    """One offline run (as `flashmono run`) of the sequence in `mode`; its metrics plus the counted events."""
    from worker.config import SlamConfig
    from worker.offline import run_sequence

    depth, posed = MODES[mode]
    config = SlamConfig.preset("rgbd", mapping={"final_refine_budget_s": 0}, **MODE_CONFIG.get(mode, {}))
    with frame_events() as events:
        metrics = run_sequence(source, out, config, use_gt_depth=depth, use_gt_poses=posed, max_frames=max_frames,
                               stride=stride, resize=size)
    counts = Counter(kind for _, kind in events)
    metrics["frame_events"] = {kind: counts.get(kind, 0) for kind in EVENT_TYPES}
    metrics["lost_spans"] = lost_spans(events, metrics["num_frames"])
    metrics["events"] = events
    return metrics


def run_visual_odometry(frames: list) -> dict:
    """The visual odometry alone over the frames (as bench/visual_odometry.py's run_vo; the ATE over the frames that
    have a ground-truth pose): trajectory ATE, frames tracked, (frame, event) list, frames/s."""
    from worker.eval import absolute_trajectory_error
    from worker.events import Initialized
    from worker.tracking.visual_odometry import VisualOdometry

    vo = VisualOdometry()
    poses, events, tracked, seconds = [], [], 0, 0.0
    for frame in frames:
        start = time.perf_counter()
        result = vo.track(frame, frame.intrinsics)
        seconds += time.perf_counter() - start
        poses.append(result.pose)
        tracked += bool(result.tracked)
        for event in result.events:
            if isinstance(event, Initialized):  # the initialisation rewrites the poses of the frames before it
                for index, pose in event.frames or []:
                    poses[index] = np.asarray(pose)
            events.append((frame.index, event.TYPE))
    have = [i for i, f in enumerate(frames) if f.gt_pose is not None]
    ate = absolute_trajectory_error(np.stack([poses[i] for i in have]),
                                    np.stack([frames[i].gt_pose for i in have]), "sim3")
    return {"ate_m": ate.rmse, "tracked": tracked, "frames": len(frames), "events": events,
            "fps": len(frames) / max(seconds, 1e-9)}


def _cm(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def measure(source: Path, modes: list[str], target_width: int, max_frames: int | None, stride: int, out_root: Path,
            with_vo: bool) -> list[dict]:
    """Every supported mode on one sequence; prints the motion and one table row per mode."""
    from worker.data import open_source

    probe = open_source(source, use_gt_depth=True, max_frames=max_frames, stride=stride)
    full = (probe.intrinsics.width, probe.intrinsics.height) if probe.intrinsics is not None else None
    size = resized(*full, target_width) if full else None
    frames = list(open_source(source, use_gt_depth=True, max_frames=max_frames, stride=stride, resize=size))
    has_depth = all(f.depth is not None for f in frames)
    gt = [f.gt_pose for f in frames if f.gt_pose is not None]
    has_poses = len(gt) >= 0.95 * len(frames)  # TUM: a few frames have no ground-truth partner within 20 ms
    motion = motion_summary(np.stack(gt)) if len(gt) >= 2 else None
    print(f"\n{source} ({probe.name}): {len(frames)} frames at {size[0]}x{size[1]} (from {full[0]}x{full[1]}), "
          f"depth {'yes' if has_depth else 'no'}, ground-truth poses {len(gt)}/{len(frames)}")
    if motion:
        print(f"  motion: path {motion['path_m']:.2f} m, step median {100 * motion['step_median_m']:.1f} cm "
              f"(max {100 * motion['step_max_m']:.1f}), rotation per frame median {motion['turn_median_deg']:.2f} "
              f"deg (p95 {motion['turn_p95_deg']:.2f}, max {motion['turn_max_deg']:.2f}), "
              f"{motion['turn_total_deg']:.0f} deg in all, heading first->last {motion['heading_change_deg']:.0f} deg")
    rows = []
    vo = run_visual_odometry(frames) if with_vo and "rgb" in modes and len(gt) >= 3 else None
    del frames
    for mode in modes:
        depth, posed = MODES[mode]
        if (depth and not has_depth) or (posed and not has_poses):
            why = "no depth" if depth and not has_depth else "poses for under 95 % of the frames"
            print(f"  {mode}: skipped ({why})")
            continue
        out = out_root / f"{probe.name}_{mode}"
        start = time.perf_counter()
        try:
            metrics = run_mode(source, mode, size, max_frames, stride, out)
        except (ValueError, RuntimeError) as err:  # e.g. a frame without a pose in posed mode: the next mode goes on
            print(f"| {probe.name} | {mode} | failed: {err} |", flush=True)
            rows.append({"mode": mode, "error": str(err)})
            continue
        metrics["wall_s"] = time.perf_counter() - start
        metrics["load_after"] = os.getloadavg()
        metrics["motion"] = motion
        if mode == "rgb" and vo is not None:
            metrics["visual_odometry"] = {k: vo[k] for k in ("ate_m", "tracked", "frames", "events", "fps")}
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1, default=str))
        rows.append({"mode": mode, **metrics})
        _print_row(probe.name, mode, metrics, motion)
    return rows


def _print_row(name: str, mode: str, m: dict, motion: dict | None) -> None:
    ate = m.get("ate_rmse")
    share = f"{100 * ate / motion['path_m']:.2f} %" if ate is not None and motion and motion["path_m"] > 0 else "-"
    events = ", ".join(f"{k} {v}" for k, v in m["frame_events"].items() if v) or "none"
    spans = m["lost_spans"]
    if spans:
        held = sum(b - a + 1 for a, b in spans)
        longest = max(spans, key=lambda s: s[1] - s[0])
        events += f"; {held} frames lost in {len(spans)} losses (longest {longest[0]}-{longest[1]})"
    line = (f"| {name} | {mode} | {m['num_frames']} | {m['num_keyframes']} | {_cm(ate)} | {share} | "
            f"{m['psnr']:.2f} | {_cm(m['depth_l1'])} | {m['fps']:.2f} / {m['fps_streaming']:.1f} | {events} |")
    print(line, flush=True)
    vo = m.get("visual_odometry")
    if vo:
        lost = [i for i, kind in vo["events"] if kind == "tracking_lost"]
        back = [i for i, kind in vo["events"] if kind.startswith("relocalized")]
        vo_share = f"{100 * vo['ate_m'] / motion['path_m']:.2f} %" if motion and motion["path_m"] > 0 else "-"
        print(f"|   (VO alone) | rgb | {vo['frames']} | | {_cm(vo['ate_m'])} | {vo_share} | | | {vo['fps']:.1f} | "
              f"tracked {vo['tracked']}/{vo['frames']}, lost at {lost[:8]}{'...' if len(lost) > 8 else ''}, "
              f"relocalised at {back[:8]}{'...' if len(back) > 8 else ''} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench real_sequences", description=__doc__.split("\n")[0])
    parser.add_argument("--source", type=Path, action="append", required=True, help="dataset folder (repeatable)")
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--width", type=int, default=320, help="frame width; the height keeps the aspect ratio")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="keep each run's outputs here (default: a temp dir)")
    parser.add_argument("--no-vo", action="store_true", help="skip the visual odometry alone on the RGB row")
    parser.add_argument("--record", action="store_true", help="write each mode's result record (bench/results/)")
    args = parser.parse_args(argv)
    recorder = Recorder("real_sequences", argv)
    modes = args.modes.split(",")
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        parser.error(f"unknown mode(s) {unknown}; known: {', '.join(MODES)}")
    sys.setswitchinterval(0.001)  # as `flashmono run` and the worker (client/commands/run.py)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"load before: {os.getloadavg()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print("| sequence | mode | frames | keyframes | ATE (cm) | ATE / path | PSNR | depth L1 (cm) | frames/s (end to "
          "end / streaming) | frames with events |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with contextlib.ExitStack() as stack:
        out_root = args.out or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        for source in args.source:
            rows = measure(source, modes, args.width, args.max_frames, args.stride, out_root, not args.no_vo)
            for row in rows if args.record else []:
                if "error" not in row:
                    recorder.write({"area": "real", "sequence": source.name, "mode": row["mode"].replace("_", "-"),
                                    "size": f"{args.width} wide"},
                                   {"ate_m": row.get("ate_rmse"), "psnr_db": row.get("psnr"),
                                    "depth_l1_m": row.get("depth_l1"), "fps": row.get("fps")})
    print(f"load after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
