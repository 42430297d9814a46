"""Held-out PSNR of several `flashmono run` output folders on the frames every one of them held out.

Each run scores the frames it did not take as keyframes, so two modes of one sequence (posed RGB and RGB only, say)
score different frames: the frames one mode skipped as easy (standing still, little parallax) may be frames the
other mapped. This reads each folder's metrics.json (`held_out`: the index and PSNR of every held-out frame, as
captured and exposure-normalised) and prints, per run, its own figure and the mean over the frames all the runs
held out.

A run may carry a label (`LABEL=RUN_DIR`): runs of one label are repeats of one mode (other
`mapping.final_refine_seed`s, say), and each label then gets the mean and spread of its runs on the common frames,
so that a difference between two modes can be read against how far one mode moves by chance.

Usage: python -m bench held_out -- [--sequence NAME] [LABEL=]RUN_DIR [LABEL=]RUN_DIR [...]

Each label (each run without one) is written as a record of the scoreboard's area "real": the common-frame PSNR
(`psnr_db`, `psnr_normalised_db`) of its mode on the sequence (`--sequence`, as the scoreboard names it; default
the runs' own `sequence`).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any


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


def group_summary(means: dict[str, dict[str, float]], labels: dict[str, str]) -> dict[str, dict[str, float]]:
    """Per label: the mean, sample standard deviation (0 for one run), minimum and maximum of its runs' common-frame
    PSNR (as captured), and how many runs; `labels`: run name -> label."""
    out = {}
    for label in dict.fromkeys(labels.values()):
        values = [means[name]["psnr"] for name, of in labels.items() if of == label]
        out[label] = {"mean": statistics.mean(values), "std": statistics.stdev(values) if len(values) > 1 else 0.0,
                      "min": min(values), "max": max(values), "runs": len(values)}
    return out


def records(metrics: dict[str, dict], means: dict[str, dict[str, float]], labels: dict[str, str], common: list[int],
            sequence: str | None) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(case, values) per label: area "real", the sequence, the mode (and the label, where two labels share a mode);
    values the mean common-frame PSNR of its runs (as captured and normalised), their spread and counts."""
    groups: dict[str, list[str]] = {}
    for name, label in labels.items():
        groups.setdefault(label, []).append(name)
    modes = {label: str(metrics[names[0]].get("mode", "unknown")).replace("_", "-") for label, names in groups.items()}
    out = []
    for label, names in groups.items():
        psnrs = [means[name]["psnr"] for name in names]
        case = {"area": "real", "sequence": sequence or str(metrics[names[0]].get("sequence", "unknown")),
                "mode": modes[label]}
        if list(modes.values()).count(modes[label]) > 1:
            case["variant"] = label
        out.append((case, {"psnr_db": round(statistics.mean(psnrs), 3),
                           "psnr_normalised_db": round(statistics.mean(means[n]["psnr_normalised"] for n in names), 3),
                           "psnr_std_db": round(statistics.stdev(psnrs), 3) if len(psnrs) > 1 else 0.0,
                           "runs": len(names), "common_frames": len(common)}))
    return out


def _labelled(argument: str) -> tuple[str, Path]:
    label, sep, folder = argument.partition("=")
    return (label, Path(folder)) if sep and label else (argument, Path(argument))


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench held_out", description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="flashmono run output folders (metrics.json), each as LABEL=DIR to "
                        "group repeats of one mode")
    parser.add_argument("--sequence", default=None, help="the sequence's name in the records (the scoreboard's, "
                        "e.g. 'KITTI 00 frames 0-199'; default: the runs' metrics.json `sequence`)")
    args = parser.parse_args(argv)
    from bench.record import Recorder

    recorder = Recorder("held_out", argv)
    labels = {str(folder): label for label, folder in map(_labelled, args.runs)}
    metrics = {name: json.loads((Path(name) / "metrics.json").read_text()) for name in labels}
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
    if len(set(labels.values())) < len(labels):
        for label, g in group_summary(means, labels).items():
            print(f"  {label}: {g['runs']} runs, common frames {g['mean']:.3f} +- {g['std']:.3f} dB "
                  f"(min {g['min']:.2f}, max {g['max']:.2f})")
    for case, values in records(metrics, means, labels, common, args.sequence):
        recorder.write(case, values, compared=list(labels))
    return 0
