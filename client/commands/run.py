"""`flashmono run SOURCE --out DIR`: run the SLAM engine offline on a sequence and write trajectories, the map,
renders and metrics.json (see worker.offline)."""

from __future__ import annotations

import argparse
import json
import sys

from client.commands._options import parse_size

# Seconds the final refinement of an offline run may take by default, after the mapping stage drained (0: it
# completes its passes). Measured on 2 cores: TUM fr1/xyz RGB-D completes them in 54 s, but ICL needs more, and a
# 60 s bound cost ICL 1-2.4 dB (RGB-D 28.52, RGB only 28.34, posed RGB 27.08 dB), so no bound by default.
DEFAULT_FINISH_BUDGET_S = 0.0


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by `run` and `eval`."""
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--use-gt-depth", action="store_true", help="RGB-D mode: use the dataset's depth")
    parser.add_argument("--use-gt-poses", action="store_true", help="posed mode: use the dataset's poses")
    parser.add_argument("--preset", default=None,
                        help="SlamConfig preset: paper, default, fast, rgbd, test (default: chosen from the input and "
                        "this machine as for a session that names none, worker.settings_choice: rgbd on a CPU, "
                        "paper with a CUDA GPU and trained weights given by FLASHMONO_CHECKPOINT)")
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
    parser.add_argument("--finish-budget", type=float, default=None, metavar="SECONDS",
                        help="bound the final refinement at the end of the run to this many seconds (default 0: no "
                        "bound, it completes its passes, at most passes x held keyframe images iterations; with a "
                        "bound its learning rates follow the time left, so the map then depends on the machine's "
                        "speed). The mapping of the keyframes still waiting when the last frame is tracked comes "
                        "before it and is not bounded")
    parser.add_argument("--live-pacing", action="store_true",
                        help="shed mapping work as a live session does when mapping falls behind (default: an "
                        "offline run refines every keyframe, so its map does not depend on the machine's load)")
    parser.add_argument("--deterministic", action="store_true",
                        help="run every stage inline, in order (SlamConfig.threaded false): the same input gives the "
                        "same map and metrics on any machine, for comparing two modes or two versions; the map "
                        "misses the refinement a threaded run does while mapping waits for keyframes (ICL posed RGB: "
                        "0.3-0.6 dB lower)")
    parser.add_argument("--eval-frames", type=int, default=None, metavar="N",
                        help="score the map on at most N held-out frames, evenly spread (default 200; 0: every one)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def load_config(args: argparse.Namespace):
    """The SlamConfig from --preset and --config."""
    from worker.config import SlamConfig, deep_merge

    overrides = {}
    if args.config:
        try:
            with open(args.config) as fh:
                overrides = json.load(fh)
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"cannot read config overrides {args.config}: {err}") from err
        if not isinstance(overrides, dict):
            raise ValueError("--config must hold a JSON object")
    if args.preset:
        config = SlamConfig.preset(args.preset, **overrides)
    else:
        choice = _auto_settings(args)
        config = SlamConfig.preset(choice.preset, **deep_merge(choice.engine_overrides(), overrides))
    if getattr(args, "deterministic", False):
        config = config.model_copy(update={"threaded": False})
    budget = finish_budget(args)
    if budget is not None and "final_refine_budget_s" not in overrides.get("mapping", {}):
        # an offline run: the budget is the final refinement's own, not shared with the drain before it
        config = config.model_copy(update={"mapping": config.mapping.model_copy(
            update={"final_refine_budget_s": budget, "final_refine_budget_counts_drain": False})})
    return config


def finish_budget(args: argparse.Namespace) -> float | None:
    """--finish-budget, else DEFAULT_FINISH_BUDGET_S (never a time bound with --deterministic: it would make the
    refinement's learning rates depend on the machine's speed). None: the config's own."""
    if not hasattr(args, "finish_budget"):
        return None
    budget = args.finish_budget
    if budget is None:
        budget = 0.0 if getattr(args, "deterministic", False) else DEFAULT_FINISH_BUDGET_S
    if budget < 0:
        raise ValueError("--finish-budget must be >= 0 seconds")
    return budget


def default_preset(args: argparse.Namespace) -> str:
    """--preset, else what a session that names none gets on this machine for this input (a recording: every frame
    tracked at its size), as worker.settings_choice decides."""
    return args.preset or _auto_settings(args).preset


def _auto_settings(args: argparse.Namespace):
    from worker.settings_choice import Machine, SessionInput, choose_settings

    received = SessionInput(depth=bool(getattr(args, "use_gt_depth", False)),
                            device_poses=bool(getattr(args, "use_gt_poses", False)), live=False)
    return choose_settings(received, Machine.detect())


def run_one(args: argparse.Namespace, source: str, out_dir: str) -> dict:
    """Run one sequence with progress bars (the frames, then each phase of the finish with its estimate); returns
    its metrics."""
    from tqdm import tqdm

    from worker.offline import PoseDrift, run_sequence

    config = load_config(args)
    drift = PoseDrift(*args.drift) if args.drift else None
    bar = tqdm(desc=str(source), unit="frame", disable=args.no_progress, file=sys.stderr)
    finish = FinishBars(disable=args.no_progress)

    def progress(done: int, total: int | None) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        return run_sequence(source, out_dir, config, use_gt_depth=args.use_gt_depth, use_gt_poses=args.use_gt_poses,
                            max_frames=args.max_frames, stride=args.stride, resize=args.resize, drift=drift,
                            progress=progress, unknown_intrinsics=args.unknown_intrinsics,
                            pingpong=args.pingpong, live_pacing=args.live_pacing, scale=args.scale,
                            finish_progress=finish.update, **_eval_frames(args))
    finally:
        bar.close()
        finish.close()


def _eval_frames(args: argparse.Namespace) -> dict:
    frames = getattr(args, "eval_frames", None)
    if frames is not None and frames < 0:
        raise ValueError("--eval-frames must be >= 0")
    return {} if frames is None else {"max_eval_frames": frames}


FINISH_LABELS = {"mapping": "mapping the last keyframes", "loop_closing": "closing the last loops",
                 "refining": "final refinement"}


class FinishBars:
    """One progress bar per phase of the finish (worker.pipeline.finish_status), with the time left."""

    def __init__(self, disable: bool = False) -> None:
        self.disable = disable
        self._bar = None
        self._phase: str | None = None

    def update(self, status: dict) -> None:
        from tqdm import tqdm

        phase = status.get("phase")
        if phase != self._phase:
            self.close()
            self._phase = phase
            if phase in FINISH_LABELS and status.get("total"):
                unit = "keyframe" if phase == "mapping" else "step"
                self._bar = tqdm(desc=FINISH_LABELS[phase], total=status["total"], unit=unit, disable=self.disable,
                                 file=sys.stderr)
        if self._bar is not None:
            self._bar.update(status["done"] - self._bar.n)
            eta = status.get("eta_s")
            self._bar.set_postfix_str("" if eta is None else f"about {eta:.0f} s left", refresh=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


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
