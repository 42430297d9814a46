"""`flashmono run SOURCE --out DIR`: run the SLAM engine offline on a sequence and write trajectories, the map,
renders and metrics.json (see worker.engine.offline)."""

from __future__ import annotations

import argparse
import json
import sys

from client.commands._options import parse_size


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by `run` and `eval`."""
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--use-gt-depth", action="store_true", help="RGB-D mode: use the dataset's depth")
    parser.add_argument("--use-gt-poses", action="store_true", help="posed mode: use the dataset's poses")
    parser.add_argument("--preset", default=None,
                        help="SlamConfig preset: paper, default, fast, rgbd, test (default: rgbd, the CPU mapping "
                        "settings measured on ICL for every geometric input mode)")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    parser.add_argument("--stride", type=int, default=1, help="keep every S-th frame")
    parser.add_argument("--resize", type=parse_size, default=None, help="resize frames to WxH, e.g. 320x240")
    parser.add_argument("--config", default=None, help="JSON file of SlamConfig overrides (nested sections)")
    parser.add_argument("--drift", type=float, nargs=2, default=None, metavar=("DEG", "M"),
                        help="posed mode: inject odometry drift of DEG degrees and M metres per frame")
    parser.add_argument("--unknown-intrinsics", action="store_true",
                        help="withhold the dataset's camera intrinsics: the system estimates them (reported in "
                        "metrics.json and intrinsics.json)")
    parser.add_argument("--pingpong", type=int, default=1, metavar="N",
                        help="play a dataset folder forward and back N sweeps (a long session revisiting places)")
    parser.add_argument("--scale", type=float, default=1.0, metavar="S",
                        help="multiply every pose and depth by S: the same scene in other length units (a map that "
                        "follows the scene renders the same; ATE and depth L1 come out S times larger)")
    parser.add_argument("--finish-budget", type=float, default=0.0, metavar="SECONDS",
                        help="bound the final refinement at the end of the run (default 0: no bound, an offline run "
                        "completes its passes, at most passes x held keyframe images iterations; live sessions keep "
                        "the config's mapping.final_refine_budget_s)")
    parser.add_argument("--live-pacing", action="store_true",
                        help="shed mapping work as a live session does when mapping falls behind (default: an "
                        "offline run refines every keyframe, so its map does not depend on the machine's load)")
    parser.add_argument("--deterministic", action="store_true",
                        help="run every stage inline, in order (SlamConfig.threaded false): the same input gives the "
                        "same map and metrics on any machine, for comparing two modes or two versions; the map "
                        "misses the refinement a threaded run does while mapping waits for keyframes (ICL posed RGB: "
                        "0.3-0.6 dB lower)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def load_config(args: argparse.Namespace):
    """The SlamConfig from --preset and --config."""
    from worker.config import SlamConfig

    overrides = {}
    if args.config:
        try:
            with open(args.config) as fh:
                overrides = json.load(fh)
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"cannot read config overrides {args.config}: {err}") from err
        if not isinstance(overrides, dict):
            raise ValueError("--config must hold a JSON object")
    config = SlamConfig.preset(default_preset(args), **overrides)
    if getattr(args, "deterministic", False):
        config = config.model_copy(update={"threaded": False})
    budget = getattr(args, "finish_budget", None)
    if budget is not None and "final_refine_budget_s" not in overrides.get("mapping", {}):
        if budget < 0:
            raise ValueError("--finish-budget must be >= 0 seconds")
        config = config.model_copy(update={"mapping": config.mapping.model_copy(
            update={"final_refine_budget_s": budget})})
    return config


def default_preset(args: argparse.Namespace) -> str:
    """--preset, else `rgbd`: the CPU mapping settings measured on ICL, for depth from a sensor or from multi-view
    stereo alike (the learned model's path has its own presets: default, paper)."""
    return args.preset or "rgbd"


def run_one(args: argparse.Namespace, source: str, out_dir: str) -> dict:
    """Run one sequence with a tqdm progress bar; returns its metrics."""
    from tqdm import tqdm

    from worker.engine.offline import PoseDrift, run_sequence

    config = load_config(args)
    drift = PoseDrift(*args.drift) if args.drift else None
    bar = tqdm(desc=str(source), unit="frame", disable=args.no_progress, file=sys.stderr)

    def progress(done: int, total: int | None) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        return run_sequence(source, out_dir, config, use_gt_depth=args.use_gt_depth, use_gt_poses=args.use_gt_poses,
                            max_frames=args.max_frames, stride=args.stride, resize=args.resize, drift=drift,
                            progress=progress, unknown_intrinsics=args.unknown_intrinsics,
                            pingpong=args.pingpong, live_pacing=args.live_pacing, scale=args.scale)
    finally:
        bar.close()


# How long the tracking thread may wait for the GIL when it comes back from a compiled kernel while the mapping or
# loop-closing thread runs Python (the interpreter's default, 5 ms, is as long as a whole RGB-D alignment); the worker
# does the same (FLASHMONO_SWITCH_INTERVAL_MS).
SWITCH_INTERVAL_S = 0.001


def _run(args: argparse.Namespace) -> int:
    from worker.data import DatasetError

    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        metrics = run_one(args, args.source, args.out)
    except (ValueError, DatasetError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    keys = ("ate_rmse", "psnr", "ssim", "lpips", "depth_l1", "fps", "num_gaussians", "num_keyframes", "loops")
    for key in keys:
        print(f"{key:>14}: {metrics.get(key)}")
    print(f"wrote {args.out}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("run", help="run SLAM offline on a sequence and evaluate it",
                                   description=__doc__)
    parser.add_argument("source", help="dataset folder, video, image folder or synthetic:// URI")
    add_run_options(parser)
    parser.set_defaults(func=_run)
