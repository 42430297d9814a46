"""Held-out PSNR of several `flashmono run` output folders on the frames every one of them held out.

Each run scores the frames it did not take as keyframes, so two modes of one sequence (posed RGB and RGB only, say)
score different frames: the frames one mode skipped as easy (standing still, little parallax) may be frames the
other mapped. This reads each folder's metrics.json (`held_out`: the index and PSNR of every held-out frame, as
captured and exposure-normalised) and prints, per run, its own figure and the mean over the frames all the runs
held out.

Usage: python -m bench held_out -- RUN_DIR RUN_DIR [...]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def common_scores(runs: dict[str, dict]) -> tuple[list[int], dict[str, dict[str, float]]]:
    """(the frame indices every run held out, per run: mean `psnr` and `psnr_normalised` over them); `runs`: name ->
    the `held_out` entry of its metrics.json."""
    common = sorted(set.intersection(*(set(held["index"]) for held in runs.values())))
    means = {}
    for name, held in runs.items():
        at = {index: n for n, index in enumerate(held["index"])}
        means[name] = {key: statistics.mean(held[key][at[i]] for i in common) if common else float("nan")
                       for key in ("psnr", "psnr_normalised")}
    return common, means


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench held_out", description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="flashmono run output folders (metrics.json)")
    args = parser.parse_args(argv)
    metrics = {str(folder): json.loads((folder / "metrics.json").read_text()) for folder in args.runs}
    missing = [name for name, m in metrics.items() if "held_out" not in m]
    if missing:
        print(f"no per-frame scores (held_out) in: {', '.join(missing)} (runs before this field was written)")
        return 1
    common, means = common_scores({name: m["held_out"] for name, m in metrics.items()})
    print(f"{len(common)} frames held out by all {len(metrics)} runs")
    for name, m in metrics.items():
        print(f"  {name}: mode {m.get('mode')}, own {m['eval_frames']} frames {m['psnr']:.2f} / "
              f"{m['psnr_normalised']:.2f} dB; common frames {means[name]['psnr']:.2f} / "
              f"{means[name]['psnr_normalised']:.2f} dB (as captured / normalised)")
    return 0
