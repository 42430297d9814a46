"""End-to-end SLAM runs on ICL (the full 211-frame set when present, else tests/data/icl_mini) for each mode:
posed RGB-D (ground-truth depth and poses), posed with injected drift + loop closure, and monocular with the
default model. Prints ATE, PSNR/SSIM, depth L1, Gaussians and end-to-end FPS (paper appendix E).

`python -m bench slam [--frames N] [--size WxH] [--modes rgbd,drift,mono] [--preset fast]`
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

SHARED = Path("/work/shared/data/icl_livingroom1_micro")
MINI = Path(__file__).resolve().parents[1] / "tests" / "data" / "icl_mini"


def _source(stride_full: int) -> tuple[Path, int]:
    return (SHARED, stride_full) if SHARED.is_dir() else (MINI, 1)


def main(argv: list[str]) -> int:
    from worker.config import SlamConfig
    from worker.engine.offline import PoseDrift, run_sequence
    from worker.engine.stage_times import breakdown_table

    parser = argparse.ArgumentParser(prog="python -m bench slam")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--modes", default="rgbd,drift,mono")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--stride", type=int, default=3, help="stride on the full 211-frame set")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    source, stride = _source(args.stride)
    runs = {
        "rgbd": dict(config=SlamConfig.preset(args.preset, input={"pose_mode": "fixed", "surfel_init": "depth"}),
                     use_gt_depth=True, use_gt_poses=True),
        "drift": dict(config=SlamConfig.preset(args.preset, mapping={"enabled": False},
                                               input={"surfel_init": "depth"}),
                      use_gt_depth=True, use_gt_poses=True, drift=PoseDrift(0.1, 0.002)),
        "mono": dict(config=SlamConfig.preset(args.preset), use_gt_depth=False, use_gt_poses=False),
    }
    print(f"source {source} stride {stride} at {width}x{height}, preset {args.preset}")
    print("| mode | frames | keyframes | loops | ATE (cm) | ATE drift only (cm) | PSNR | SSIM | depth L1 (cm) "
          "| Gaussians | FPS |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    breakdowns = {}
    for mode in args.modes.split(","):
        with tempfile.TemporaryDirectory() as out:
            m = run_sequence(source, out, stride=stride, max_frames=args.frames, resize=(width, height),
                             **runs[mode])

        def cm(v):
            return "-" if v is None else f"{100 * v:.2f}"

        def num(v, d=2):
            return "-" if v is None else f"{v:.{d}f}"

        print(f"| {mode} | {m['num_frames']} | {m['num_keyframes']} | {m['loops']} | {cm(m['ate_rmse'])} | "
              f"{cm(m.get('ate_rmse_drift_only'))} | {num(m['psnr'])} | {num(m['ssim'], 3)} | {cm(m['depth_l1'])} | "
              f"{m['num_gaussians']} | {num(m['fps'], 3)} |", flush=True)
        breakdowns[mode] = (m["runtime_breakdown"], m["num_frames"])
    for mode, (breakdown, frames) in breakdowns.items():  # paper appendix E, Table 8
        print(f"\nruntime breakdown, {mode}:\n{breakdown_table(breakdown, frames)}")
    return 0
