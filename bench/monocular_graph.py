"""RGB only, `flashmono run` defaults, and with the pose graph of visual-odometry sessions set for a drifting scale
(`drift`: the odometry's log-scale free at 0.03 a keyframe, loops at their measured uncertainty, 4 % in translation
and 5 % in scale, robust kernel 3; `loop.monocular_*`), in the same run.

    python -m bench monocular_graph [--source DIR ...] [--size 320x240] [--variants defaults drift]

Default sources: the shared TUM fr1/xyz and ICL living room folders. Per sequence and variant it records ATE
(Sim(3)-aligned, all frames and keyframes only), PSNR and depth L1 on the held-out frames, keyframes, loops, wall
time and the machine's load, to bench/results/monocular_graph/.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from bench.covisible_edges import DEFAULT_SOURCES, run_loop_variant
from bench.record import Recorder, loadavg

# Measured on TUM fr1/xyz's visual odometry (bench/journal/62): its scale drift and its loops' errors.
DRIFT = {"monocular_robust_k": 3.0, "monocular_scale_sigma": 0.03, "monocular_loop_translation_sigma": 0.04,
         "monocular_loop_scale_sigma": 0.05}
VARIANTS = {"defaults": {}, "drift": DRIFT}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench monocular_graph", description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, action="append", help="a sequence folder (repeatable)")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--variants", nargs="*", choices=tuple(VARIANTS), default=list(VARIANTS))
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    recorder = Recorder("monocular_graph", argv)
    for source in args.source or [s for s in DEFAULT_SOURCES if s.is_dir()]:
        for variant in args.variants:
            load_start = loadavg()
            with tempfile.TemporaryDirectory(prefix="bench-monocular-") as tmp:
                values = run_loop_variant(source, size, VARIANTS[variant], Path(tmp), use_gt_depth=False)
            print(f"{source.name} {variant}: ATE {100 * values['ate_m']:.2f} cm (keyframes "
                  f"{100 * (values['keyframe_ate_m'] or float('nan')):.2f}), PSNR {values['psnr_db']:.2f} dB, "
                  f"{values['loops']} loops, {values['wall_s']:.0f} s", flush=True)
            recorder.write({"area": "rgb", "sequence": source.name, "mode": "rgb", "size": args.size,
                            "variant": f"graph-{variant}"}, values, load_at_case_start=load_start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
