"""RGB-D without poses, `flashmono run` defaults, with and without the dense edges between neighbouring keyframes
(`loop.covisible_neighbours`, worker.loop.keyframe_alignment), in the same run, beside Open3D's RGB-D odometry (the
peer, frame to frame, no loop closure) on the same frames.

    python -m bench covisible_edges [--source DIR ...] [--size 320x240] [--variants on off] [--no-peer]
                                    [--pingpong N]

Default sources: the shared TUM fr1/xyz and ICL living room folders. Other real sequences (a TUM folder fetched, not
shipped) are given with --source. Per sequence and variant it records ATE (SE(3)-aligned, all frames and keyframes
only), PSNR and depth L1 on the held-out frames, keyframes, loops, covisible edges kept, wall time and the machine's
load, to bench/results/covisible_edges/.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.record import Recorder, loadavg

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULT_SOURCES = (SHARED / "tum_fr1_xyz", SHARED / "icl_livingroom1_micro")


def run_variant(source: Path, size: tuple[int, int], neighbours: int | None, out: Path, pingpong: int = 1
                ) -> dict[str, Any]:
    """`flashmono run SOURCE --use-gt-depth [--pingpong N]` with its default settings; `neighbours` overrides the
    edges' count."""
    return run_loop_variant(source, size, {} if neighbours is None else {"covisible_neighbours": neighbours}, out,
                            use_gt_depth=True, pingpong=pingpong)


def run_loop_variant(source: Path, size: tuple[int, int], loop_update: dict[str, Any], out: Path,
                     use_gt_depth: bool, pingpong: int = 1) -> dict[str, Any]:
    """`flashmono run SOURCE [--use-gt-depth] [--pingpong N]` with its default settings but `loop_update` in the
    loop section (see `run_configured`)."""
    return run_configured(source, size, {"loop": loop_update}, out, use_gt_depth, pingpong=pingpong)


def run_configured(source: Path, size: tuple[int, int], overrides: dict[str, Any], out: Path, use_gt_depth: bool,
                   use_gt_poses: bool = False, pingpong: int = 1) -> dict[str, Any]:
    """`flashmono run SOURCE [--use-gt-depth] [--use-gt-poses] [--pingpong N]` with its default settings and the
    nested section `overrides` merged in; ATE, keyframe ATE (SE(3) with depth or poses, Sim(3) without), PSNR,
    depth L1, keyframes, loops, the pose source chosen, wall."""
    from client.commands.run import load_config
    from worker.config import SlamConfig, deep_merge
    from worker.eval import read_tum
    from worker.offline import run_sequence

    config = load_config(argparse.Namespace(use_gt_depth=use_gt_depth, use_gt_poses=use_gt_poses, preset=None,
                                            config=None, finish_budget=None, deterministic=False))
    config = SlamConfig.model_validate(deep_merge(config.model_dump(), overrides))
    start = time.perf_counter()
    metrics = run_sequence(str(source), out, config, use_gt_depth=use_gt_depth, use_gt_poses=use_gt_poses,
                           resize=size, pingpong=pingpong)
    wall = time.perf_counter() - start
    keyframes = read_tum(out / "trajectory_keyframes.tum")
    alignment = "se3" if use_gt_depth or use_gt_poses else "sim3"
    return {"ate_m": metrics.get("ate_rmse"),
            "keyframe_ate_m": _keyframe_ate(source, size, keyframes, alignment) if pingpong == 1 else None,
            "psnr_db": metrics.get("psnr"), "depth_l1_m": metrics.get("depth_l1"),
            "keyframes": metrics.get("num_keyframes"), "loops": metrics.get("loops"),
            "events": metrics.get("events"), "frames": metrics.get("num_frames"), "wall_s": round(wall, 1),
            "pose_source": metrics.get("pose_source"),
            "keyframe_alignment": (metrics.get("runtime_breakdown") or {}).get("keyframe_alignment")}


def _keyframe_ate(source: Path, size: tuple[int, int], keyframes, alignment: str = "se3") -> float | None:
    """ATE of the keyframes alone against the sequence's ground truth (`alignment` se3 or sim3)."""
    from worker.data import open_source
    from worker.eval import absolute_trajectory_error

    truth = {round(f.timestamp, 6): f.gt_pose for f in open_source(str(source), resize=size, use_gt_depth=False)
             if f.gt_pose is not None}
    pairs = [(p, truth[round(float(t), 6)]) for t, p in zip(keyframes.timestamps, keyframes.poses)
             if round(float(t), 6) in truth]
    if len(pairs) < 3:
        return None
    return absolute_trajectory_error(np.stack([p for p, _ in pairs]), np.stack([g for _, g in pairs]), alignment).rmse


def run_peer(source: Path, size: tuple[int, int]) -> dict[str, Any]:
    """Open3D's hybrid RGB-D odometry, frame to frame, on the same frames (a bench extra: `pip install open3d`)."""
    from bench.rgbd_odometry import run_open3d
    from worker.data import open_source
    from worker.eval import absolute_trajectory_error

    src = open_source(str(source), resize=size, use_gt_depth=True, use_gt_poses=False)
    frames = list(src)
    try:
        poses, seconds, lost = run_open3d(frames, src.intrinsics)
    except ImportError as error:
        return {"error": f"not installed ({error})"}
    known = [i for i, f in enumerate(frames) if f.gt_pose is not None]
    truth = np.stack([frames[i].gt_pose for i in known])
    return {"ate_m": absolute_trajectory_error(poses[known], truth, "se3").rmse,
            "ms_per_frame": round(1e3 * seconds, 1),
            "frames_lost": lost, "frames": len(frames)}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench covisible_edges", description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, action="append", help="a sequence folder (repeatable)")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--variants", nargs="*", choices=("on", "off"), default=["on", "off"])
    parser.add_argument("--no-peer", action="store_true", help="leave Open3D out")
    parser.add_argument("--pingpong", type=int, default=1, help="play each sequence forward and back N sweeps (a "
                        "long session coming back to its places)")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    recorder = Recorder("covisible_edges", argv)
    for source in args.source or [s for s in DEFAULT_SOURCES if s.is_dir()]:
        for variant in args.variants:
            load_start = loadavg()
            with tempfile.TemporaryDirectory(prefix="bench-covisible-") as tmp:
                values = run_variant(source, size, None if variant == "on" else 0, Path(tmp), args.pingpong)
            print(f"{source.name} {variant}: ATE {100 * values['ate_m']:.2f} cm (keyframes "
                  f"{100 * (values['keyframe_ate_m'] or float('nan')):.2f}), PSNR {values['psnr_db']:.2f} dB, "
                  f"{values['keyframes']} keyframes, {values['wall_s']:.0f} s", flush=True)
            sequence = source.name if args.pingpong == 1 else f"{source.name}_pingpong{args.pingpong}"
            recorder.write({"area": "rgbd", "sequence": sequence, "mode": "rgbd", "size": args.size,
                            "variant": f"covisible-{variant}"}, values, load_at_case_start=load_start)
        if not args.no_peer and args.pingpong == 1:
            load_start = loadavg()
            values = run_peer(source, size)
            print(f"{source.name} Open3D odometry: {values}", flush=True)
            recorder.write({"area": "rgbd", "sequence": source.name, "mode": "rgbd", "size": args.size,
                            "variant": "open3d-odometry"}, values, load_at_case_start=load_start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
