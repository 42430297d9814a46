"""Hole filling of multi-view depth (worker.depth.hole_fill) on ICL, and the holes left in held-out renders.

ICL: 211 frames at 320x240 with ground-truth poses; every 6th frame is a keyframe whose neighbours
`select_neighbours` picks (as `python -m bench mvs` does, depth range from 200 random pixels' depth). Per keyframe:
the confident multi-view depth, then `fill_depth`; reported: the fraction of pixels filled, the L1 error of the
filled pixels against ICL's depth (and their median relative error), the coverage and the largest hole (the largest
4-connected region without depth, % of the image) before and after, and the fill's time. Then the keyframes' planes
(worker.depth.world_planes, as the engine does: each keyframe in order adds its confident points to the memory and
is filled from its planes): the keyframe depth's L1 and coverage of the pixels with ground truth, and the keyframes
meeting issue 21's real-sequence target (<= 10 cm at >= 70 %). `--data` takes any folder `open_source` reads
(a TUM RGB-D folder too).

Renders: `--renders DIR [DIR ...]` reads `flashmono run` output folders (renders/NNNNN.png: render | ground truth)
and reports the largest hole in each held-out render (pixels the render leaves black, all channels <= 2, where the
ground truth is not), % of the image, mean and worst over the frames.

Usage: python -m bench hole_fill [-- --every 6 --renders /tmp/run_a /tmp/run_b]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from bench.mvs import _K, DATA, _range_from_points
from bench.record import Recorder
from bench.render import machine


def largest_hole(empty: np.ndarray) -> float:
    """The largest 4-connected region of `empty` (bool [H, W]) as a fraction of the image."""
    if not empty.any():
        return 0.0
    count, labels, stats, _ = cv2.connectedComponentsWithStats(empty.astype(np.uint8), connectivity=4)
    return float(stats[1:, cv2.CC_STAT_AREA].max()) / empty.size


def record(rows: list[dict], args: argparse.Namespace) -> tuple[dict, dict]:
    """(case, values) of the keyframes' depth (area "real", posed RGB): the keyframe depth as the engine makes it
    (stereo, hole fill, planes, border planes) against the sensor's, mean over the keyframes; the earlier stages'
    figures beside."""
    def mean(key: str) -> float | None:
        values = [r[key] for r in rows if np.isfinite(r[key])]
        return round(statistics.mean(values), 5) if values else None

    sequence = args.sequence or ("ICL living room" if args.data == DATA else args.data.name)
    case = {"area": "real", "sequence": sequence, "mode": "posed-rgb"}
    settings = ([] if args.every == 6 else [f"every {args.every}"]) + (
        [] if tuple(args.resize) == (320, 240) else ["x".join(map(str, args.resize))])
    if settings:
        case["variant"] = ", ".join(settings)
    values = {"depth_l1_m": mean("borders_l1"), "depth_coverage_share": mean("borders_cov"),
              "planes_depth_l1_m": mean("planes_l1"), "planes_coverage_share": mean("planes_cov"),
              "stereo_depth_l1_m": mean("stereo_l1"), "stereo_coverage_share": mean("cov_before"),
              "filled_share": mean("filled"), "keyframes": len(rows),
              "keyframes_meeting_target": sum(r["borders_l1"] <= 0.1 and r["borders_cov"] >= 0.7 for r in rows)}
    return case, values


def bench_icl(args, recorder: Recorder | None = None) -> list[str]:
    from worker.data import open_source
    from worker.depth import MultiViewDepthConfig, estimate_depth, select_neighbours
    from worker.depth.border_planes import fill_from_borders
    from worker.depth.hole_fill import fill_depth
    from worker.depth.world_planes import PlaneMemory, fill_from_planes

    config = MultiViewDepthConfig()
    frames = list(open_source(args.data, resize=args.resize, use_gt_depth=True, use_gt_poses=True))
    K = _K(frames[0].intrinsics)
    rng = np.random.default_rng(0)
    rows = []
    memory = PlaneMemory()
    for k in range(0, len(frames), args.every):
        frame = frames[k]
        depth_range, scene_depth = _range_from_points(frame.depth, rng)
        others = [i for i in range(len(frames)) if i != k]
        chosen = select_neighbours(frame.pose, [frames[i].pose for i in others], config, scene_depth)
        neighbours = [(frames[others[i]].image, frames[others[i]].pose) for i in chosen]
        stereo = estimate_depth(frame.image, K, frame.pose, neighbours, depth_range, config).depth
        start = time.perf_counter()
        result = fill_depth(stereo, frame.image)
        ms = 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
        memory.add(k, stereo, frame.pose, K)
        planed, _ = fill_from_planes(result.depth, frame.image, memory.planes(), frame.pose, K, memory.settings)
        planes_ms = 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
        bordered, _ = fill_from_borders(planed, frame.image, memory.planes(), frame.pose, K)
        borders_ms = 1000 * (time.perf_counter() - start)
        gt = frame.depth
        filled = result.filled & (gt > 0)
        with_gt = (planed > 0) & (gt > 0)
        bordered_gt = (bordered > 0) & (gt > 0)
        row = {"filled": result.fill_fraction, "cov_before": float((stereo > 0).mean()),
               "cov_after": float((result.depth > 0).mean()), "hole_before": largest_hole(stereo <= 0),
               "hole_after": largest_hole(result.depth <= 0), "ms": ms,
               "l1": float(np.abs(result.depth[filled] - gt[filled]).mean()) if filled.any() else float("nan"),
               "rel": float(np.median(np.abs(result.depth[filled] - gt[filled]) / gt[filled])) if filled.any()
               else float("nan"),
               "stereo_l1": float(np.abs(stereo[(stereo > 0) & (gt > 0)] - gt[(stereo > 0) & (gt > 0)]).mean()),
               "planes_l1": float(np.abs(planed[with_gt] - gt[with_gt]).mean()) if with_gt.any() else float("nan"),
               "planes_cov": float(with_gt.sum() / max((gt > 0).sum(), 1)), "planes_ms": planes_ms,
               "borders_l1": float(np.abs(bordered[bordered_gt] - gt[bordered_gt]).mean()) if bordered_gt.any()
               else float("nan"),
               "borders_cov": float(bordered_gt.sum() / max((gt > 0).sum(), 1)), "borders_ms": borders_ms}
        rows.append(row)
        print(f"  kf {k:>3}: filled {100 * row['filled']:5.1f} %  L1 filled {100 * row['l1']:5.2f} cm "
              f"(stereo {100 * row['stereo_l1']:5.2f})  coverage {100 * row['cov_before']:5.1f} -> "
              f"{100 * row['cov_after']:5.1f} %  largest hole {100 * row['hole_before']:5.1f} -> "
              f"{100 * row['hole_after']:5.1f} %  {ms:6.1f} ms | + planes: L1 {100 * row['planes_l1']:5.2f} cm @ "
              f"{100 * row['planes_cov']:5.1f} % {planes_ms:6.1f} ms | + borders: L1 "
              f"{100 * row['borders_l1']:5.2f} cm @ "
              f"{100 * row['borders_cov']:5.1f} % {borders_ms:6.1f} ms", flush=True)
    if recorder is not None:
        recorder.write(*record(rows, args))
    l1 = [r["l1"] for r in rows if np.isfinite(r["l1"])]
    mean = {key: statistics.mean(r[key] for r in rows) for key in ("filled", "cov_before", "cov_after",
                                                                  "hole_before", "hole_after", "stereo_l1")}
    return [f"{args.data.name} keyframes {len(rows)}: filled {100 * mean['filled']:.1f} % of the pixels; filled "
            f"pixels' depth L1 "
            f"{100 * statistics.mean(l1):.2f} cm (median relative error "
            f"{100 * statistics.median(r['rel'] for r in rows if np.isfinite(r['rel'])):.1f} %; confident stereo "
            f"{100 * mean['stereo_l1']:.2f} cm); coverage {100 * mean['cov_before']:.1f} -> "
            f"{100 * mean['cov_after']:.1f} %; largest hole mean {100 * mean['hole_before']:.1f} -> "
            f"{100 * mean['hole_after']:.1f} % (worst {100 * max(r['hole_before'] for r in rows):.1f} -> "
            f"{100 * max(r['hole_after'] for r in rows):.1f} %); fill time median "
            f"{statistics.median(r['ms'] for r in rows):.0f} ms",
            f"+ planes of the keyframes (world_planes): keyframe depth L1 "
            f"{100 * statistics.mean(r['planes_l1'] for r in rows if np.isfinite(r['planes_l1'])):.2f} cm at "
            f"{100 * statistics.mean(r['planes_cov'] for r in rows):.1f} % coverage (mean over keyframes); keyframes "
            f"meeting <= 10 cm @ >= 70 %: {sum(r['planes_l1'] <= 0.1 and r['planes_cov'] >= 0.7 for r in rows)}/"
            f"{len(rows)}; planes time median {statistics.median(r['planes_ms'] for r in rows):.0f} ms",
            f"+ border planes (border_planes): keyframe depth L1 "
            f"{100 * statistics.mean(r['borders_l1'] for r in rows if np.isfinite(r['borders_l1'])):.2f} cm at "
            f"{100 * statistics.mean(r['borders_cov'] for r in rows):.1f} % coverage; keyframes meeting <= 10 cm @ "
            f">= 70 %: {sum(r['borders_l1'] <= 0.1 and r['borders_cov'] >= 0.7 for r in rows)}/{len(rows)}; time "
            f"median {statistics.median(r['borders_ms'] for r in rows):.0f} ms"]


def render_holes(folder: Path) -> str:
    """Largest black region of each held-out render of a `flashmono run` output folder."""
    holes = []
    for path in sorted((folder / "renders").glob("*.png")):
        side = cv2.imread(str(path))
        w = side.shape[1] // 2
        render, truth = side[:, :w], side[:, w:]
        holes.append(largest_hole((render.max(-1) <= 2) & (truth.max(-1) > 2)))
    if not holes:
        return f"{folder}: no renders"
    return (f"{folder}: {len(holes)} held-out renders, largest hole mean {100 * statistics.mean(holes):.2f} % "
            f"(worst {100 * max(holes):.2f} %) of the image")


def _size(text: str) -> tuple[int, int]:
    width, height = text.lower().split("x")
    return int(width), int(height)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench hole_fill", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="ICL living room folder (Open3D/ICL format)")
    parser.add_argument("--every", type=int, default=6, help="every n-th frame is a keyframe")
    parser.add_argument("--resize", type=_size, default=(320, 240), metavar="WxH",
                        help="frame size (default 320x240; 240x320 for portrait captures)")
    parser.add_argument("--renders", type=Path, nargs="*", default=[], help="flashmono run output folders")
    parser.add_argument("--no-icl", action="store_true")
    parser.add_argument("--sequence", default=None, help="the sequence's name in the record (the scoreboard's, "
                        "e.g. 'TUM fr3/cabinet'; default 'ICL living room' for the default --data, else its name)")
    args = parser.parse_args(argv)
    recorder = Recorder("hole_fill", argv)
    print(f"machine: {machine()}")
    lines = [] if args.no_icl or not args.data.exists() else bench_icl(args, recorder)
    lines += [render_holes(folder) for folder in args.renders]
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")
    for line in lines:
        print(line)
    return 0
