"""Device pose clock offsets: estimated on real frames, and what compensating them does to posed SLAM.

`python -m bench device_clock [--frames N] [--offsets-ms 0,20,40,-40] [--slam-offsets-ms 0,40,-40] [--slam-clock
estimate,off] [--settings defaults] [--no-slam]`

The device poses are the sequences' ground truth re-timed: a copy with a clock offset d carries, at frame time t,
the ground truth read at t + d (slerp / linear between its poses at the frames' timestamps). TUM fr1/xyz's ground truth
is motion capture on its own clock, so what the estimator finds there is that native offset plus the injected one;
ICL's poses are exact (rendered), so there it should find the injected one alone.

- `estimate` cases: `worker.tracking.device_clock.DeviceClock` with the session's defaults over the frames, with and
  without depth: the offset it measured, its uncertainty, and after how many frames.
- `slam` cases (TUM fr1/xyz, or `--slam-sequence`): `flashmono run`'s engine (worker.offline.run_sequence) in posed
  RGB-D (`pose_mode` auto = seeded) and posed RGB (auto: judged, prior or seeded), with `input.device_clock.mode`
  estimate and off; ATE against the unshifted ground truth and held-out PSNR. The SLAM runs take `flashmono run`'s
  settings for their input on this machine (`--settings defaults`; records before 2026-11-30 ran the `rgbd` preset,
  which maps posed RGB poorly: their variants carry no settings suffix). Records under bench/results/device_clock/.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.record import ROOT, Recorder, loadavg

DATA = ROOT.parent / "shared" / "data"
SEQUENCES = {"tum_fr1_xyz": DATA / "tum_fr1_xyz", "icl_livingroom1_micro": DATA / "icl_livingroom1_micro"}
SIZE = (320, 240)


class ShiftedPoses:
    """The ground truth of a sequence's frames, read at `timestamp + offset_s` (a device clock `offset_s` ahead)."""

    def __init__(self, times: np.ndarray, poses: np.ndarray, offset_s: float) -> None:
        from worker.tracking.pose_interpolation import interpolate_poses

        shifted = interpolate_poses(times, poses, times + offset_s, max_extrapolation_s=0.05)
        self.by_time = {round(float(t), 6): p for t, p in zip(times, shifted)}

    def __call__(self, frame) -> np.ndarray:
        return self.by_time[round(float(frame.timestamp), 6)].copy()


def ground_truth(path: Path, frames: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, c2w ground-truth poses) of the sequence's frames."""
    from worker.data import open_source

    src = open_source(str(path), use_gt_poses=True, max_frames=frames, resize=SIZE)
    pairs = [(f.timestamp, f.gt_pose) for f in src if f.gt_pose is not None]
    return np.array([t for t, _ in pairs]), np.stack([p for _, p in pairs])


def estimate_case(path: Path, frames: int | None, offset_s: float, with_depth: bool,
                  truth: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    """The DeviceClock's estimate over the sequence with device poses `offset_s` ahead of the camera."""
    from worker.data import open_source
    from worker.eval import absolute_trajectory_error
    from worker.tracking.device_clock import DeviceClock

    shifted = ShiftedPoses(*truth, offset_s)
    clock = DeviceClock(use_depth=with_depth)
    src = open_source(str(path), use_gt_poses=True, max_frames=frames, resize=SIZE)
    spent, n = 0.0, 0
    given, retimed, reference = [], [], []
    settled = None  # the first frame re-timed by the whole measured offset (it is reached by 1 ms a frame)
    for frame in src:
        frame.pose = shifted(frame)
        start = time.perf_counter()
        pose = clock.pose_at(frame, src.intrinsics)
        if clock.measuring:
            spent += time.perf_counter() - start
            n += 1
        if settled is None and not clock.measuring and clock.offset_s == clock.target_offset_s:
            settled = len(given)
        given.append(frame.pose)
        retimed.append(pose)
        reference.append(frame.gt_pose)
    clock.finish_measuring()
    estimate = clock.estimate.to_dict() if clock.estimate else {}

    def ate_cm(poses: list[np.ndarray], start: int = 0) -> float:
        return round(absolute_trajectory_error(np.stack(poses[start:]), np.stack(reference[start:]), "se3").rmse
                     * 100, 3)

    after = n + 1  # the frames after the estimate: what the session gets once it is measured
    return {"injected_ms": round(offset_s * 1000, 1), "estimated": estimate.get("estimated"),
            "estimated_ms": estimate.get("offset_ms"), "uncertainty_ms": estimate.get("uncertainty_ms"),
            "applied_ms": round(clock.offset_s * 1000, 2), "pairs": estimate.get("pairs"), "frames_to_estimate": n,
            "mean_ms_per_frame": round(spent / max(n, 1) * 1000, 2), "reason": estimate.get("reason"),
            "device_ate_cm_given": ate_cm(given), "device_ate_cm_retimed": ate_cm(retimed),
            "device_ate_cm_given_after_estimate": ate_cm(given, after),
            "device_ate_cm_retimed_after_estimate": ate_cm(retimed, after), "settled_at_frame": settled,
            "device_ate_cm_given_settled": None if settled is None else ate_cm(given, settled),
            "device_ate_cm_retimed_settled": None if settled is None else ate_cm(retimed, settled)}


def slam_case(path: Path, frames: int | None, offset_s: float, input_mode: str, mode: str,
              truth: tuple[np.ndarray, np.ndarray], settings: str = "defaults") -> dict[str, Any]:
    """A posed run (`input_mode` posed-rgbd, posed-rgb, or posed-rgb-prior: pose_mode prior, the device poses are
    the odometry) with device poses `offset_s` ahead and the device clock `mode` (estimate / off). `settings`:
    "defaults", what `flashmono run` chooses for the input on this machine (a newcomer's session), or a preset."""
    from worker.config import SlamConfig
    from worker.offline import run_sequence
    from worker.settings_choice import Machine, SessionInput, choose_settings

    with_depth = input_mode == "posed-rgbd"
    if settings == "defaults":
        choice = choose_settings(SessionInput(depth=with_depth, device_poses=True, live=False), Machine.detect())
        config = SlamConfig.preset(choice.preset, **choice.engine_overrides())
    else:
        config = SlamConfig.preset(settings)
    clock = config.input.device_clock.model_copy(update={"mode": mode})
    update: dict[str, Any] = {"device_clock": clock}
    if input_mode == "posed-rgb-prior":
        update["pose_mode"] = "prior"
    config = config.model_copy(update={"input": config.input.model_copy(update=update)})
    load = loadavg()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-device-clock-") as out:
        metrics = run_sequence(path, out, config, use_gt_depth=with_depth, use_gt_poses=True, max_frames=frames,
                               resize=SIZE, device_poses=ShiftedPoses(*truth, offset_s))
    clock_summary = metrics.get("device_clock") or {}
    return {"injected_ms": round(offset_s * 1000, 1), "clock": mode,
            "ate_cm": None if metrics.get("ate_rmse") is None else round(metrics["ate_rmse"] * 100, 3),
            "psnr_db": None if metrics.get("psnr") is None else round(metrics["psnr"], 3),
            "offset_applied_ms": clock_summary.get("offset_ms"), "estimate": clock_summary.get("estimate"),
            "pose_source": metrics.get("pose_source"), "keyframes": metrics.get("num_keyframes"),
            "wall_s": round(time.perf_counter() - start, 1), "load_start": load, "load_end": loadavg()}


def _offsets(text: str) -> list[float]:
    return [float(v) / 1000.0 for v in text.split(",") if v.strip()]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench device_clock", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=None, help="frames per sequence (default: all)")
    parser.add_argument("--offsets-ms", default="0,20,40,-40", help="injected offsets of the estimate cases")
    parser.add_argument("--slam-offsets-ms", default="0,40,-40", help="injected offsets of the SLAM runs")
    parser.add_argument("--slam-modes", default="posed-rgbd,posed-rgb,posed-rgb-prior",
                        help="SLAM inputs (posed-rgbd, posed-rgb, posed-rgb-prior)")
    parser.add_argument("--slam-sequence", default="tum_fr1_xyz", choices=sorted(SEQUENCES), help="SLAM runs on")
    parser.add_argument("--slam-clock", default="estimate,off", help="device clock modes of the SLAM runs")
    parser.add_argument("--settings", default="defaults",
                        help="SLAM runs' settings: defaults (flashmono run's for the input) or a preset (rgbd, ...)")
    parser.add_argument("--no-slam", action="store_true", help="estimates only")
    parser.add_argument("--no-estimates", action="store_true", help="SLAM runs only")
    args = parser.parse_args(argv)
    recorder = Recorder("device_clock", argv)
    size = f"{SIZE[0]}x{SIZE[1]}"
    for name, path in SEQUENCES.items():
        if args.no_estimates:
            break
        truth = ground_truth(path, args.frames)
        for with_depth in (True, False):
            for offset in _offsets(args.offsets_ms):
                values = estimate_case(path, args.frames, offset, with_depth, truth)
                case = {"area": "estimate", "sequence": name, "mode": "rgbd" if with_depth else "rgb", "size": size,
                        "variant": f"{values['injected_ms']:+.0f}ms"}
                recorder.write(case, values)
                print(f"estimate {name} {case['mode']} injected {values['injected_ms']:+.0f} ms: "
                      f"{values['estimated_ms']} +- {values['uncertainty_ms']} ms after {values['frames_to_estimate']} "
                      f"frames ({values['mean_ms_per_frame']} ms/frame); device ATE after it "
                      f"{values['device_ate_cm_given_after_estimate']} -> "
                      f"{values['device_ate_cm_retimed_after_estimate']} cm, once settled "
                      f"{values['device_ate_cm_given_settled']} -> {values['device_ate_cm_retimed_settled']} cm",
                      flush=True)
    if args.no_slam:
        return 0
    path = SEQUENCES[args.slam_sequence]
    truth = ground_truth(path, args.frames)
    frames_label = "all" if args.frames is None else str(args.frames)
    for input_mode in [m for m in args.slam_modes.split(",") if m]:
        for offset in _offsets(args.slam_offsets_ms):
            for mode in [m for m in args.slam_clock.split(",") if m]:
                values = slam_case(path, args.frames, offset, input_mode, mode, truth, args.settings)
                settings = "" if args.settings == "rgbd" else f"_{args.settings}"  # the first records: preset rgbd
                case = {"area": "slam", "sequence": args.slam_sequence, "mode": input_mode, "size": size,
                        "variant": f"{values['injected_ms']:+.0f}ms_clock-{mode}_frames-{frames_label}{settings}"}
                recorder.write(case, values)
                print(f"slam {input_mode} injected {values['injected_ms']:+.0f} ms clock {mode}: ATE "
                      f"{values['ate_cm']} cm PSNR {values['psnr_db']} dB (applied {values['offset_applied_ms']} ms, "
                      f"load {values['load_start']}-{values['load_end']}, {values['wall_s']} s)", flush=True)
    return 0
