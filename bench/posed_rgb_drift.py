"""Posed RGB (images and device poses, no depth) where `pose_mode` auto chooses seeded visual odometry: the ways the
device's scale meets the odometry's drifting one (`input.device_poses.drift_correction`: reanchor, the default,
settle, pose_graph), beside RGB only on the same frames, in the same run.

    python -m bench posed_rgb_drift [--source DIR ...] [--size 320x240] [--variants reanchor settle pose_graph rgb]

Default source: the shared TUM fr1/xyz folder, its motion capture sent as the device's poses (`auto` judges them and
picks seeded there; ICL's exact poses are taken as they are, so the setting does not reach ICL). A drive (KITTI 00,
fetched, not shipped) is given with --source and --size 620x188. Per sequence and variant it records ATE
(SE(3)-aligned with poses, Sim(3) for RGB only; all frames and keyframes), PSNR and depth L1 on the held-out frames,
keyframes, loops, the pose source chosen, wall time and the machine's load, to bench/results/posed_rgb_drift/.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from bench.covisible_edges import SHARED, run_configured
from bench.record import Recorder, loadavg

VARIANTS = ("reanchor", "settle", "pose_graph", "rgb")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench posed_rgb_drift", description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, action="append", help="a sequence folder (repeatable)")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--variants", nargs="*", choices=VARIANTS, default=list(VARIANTS))
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    recorder = Recorder("posed_rgb_drift", argv)
    for source in args.source or [SHARED / "tum_fr1_xyz"]:
        for variant in args.variants:
            posed = variant != "rgb"
            overrides = {"input": {"device_poses": {"drift_correction": variant}}} if posed else {}
            load_start = loadavg()
            with tempfile.TemporaryDirectory(prefix="bench-posed-rgb-") as tmp:
                values = run_configured(source, size, overrides, Path(tmp), use_gt_depth=False, use_gt_poses=posed)
            print(f"{source.name} {variant}: ATE {100 * values['ate_m']:.2f} cm, PSNR {values['psnr_db']:.2f} dB, "
                  f"pose source {values['pose_source']}, {values['loops']} loops, {values['wall_s']:.0f} s",
                  flush=True)
            recorder.write({"area": "posed_rgb", "sequence": source.name, "mode": "posed-rgb" if posed else "rgb",
                            "size": args.size, "variant": variant if posed else "rgb-only"}, values,
                           load_at_case_start=load_start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
