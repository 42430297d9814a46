"""Map size and merge cost over a long session: the map follows the scene, not the session.

A synthetic room (worker.data.synthetic, 320x240, the camera path looping the room again and again) is mapped with
the `rgbd` preset's mapping settings (surfels from the exact depth, ground-truth poses, one keyframe every
`--every` frames, threaded=False), so only the map is measured: surfels, the merge (fusion) time and the refinement
time per keyframe against the keyframe count, and the process RSS. `--cap 0` turns the voxel cap off (the map before
it). Usage: python -m bench map_size [-- --keyframes 300 --every 6 --cap 64 --seed 3]
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import torch

from bench.record import Recorder


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def main(argv: list[str]) -> int:
    from worker.config import SlamConfig
    from worker.data import open_source
    from worker.pipeline.map_jobs import KeyframeJob
    from worker.pipeline.mapping_stage import MappingStage
    from worker.pipeline.stage_times import StageTimes
    from worker.pipeline.surfel_init import grid_from_depth

    parser = argparse.ArgumentParser(prog="python -m bench map_size")
    parser.add_argument("--keyframes", type=int, default=300)
    parser.add_argument("--every", type=int, default=6, help="a keyframe every N frames (the rgbd preset's rule)")
    parser.add_argument("--cap", type=int, default=None, help="mapping voxel cap (default: the map's; 0 = off)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--frames", type=int, default=None,
                        help="length of the synthetic camera path (default keyframes x every; longer: stop early)")
    parser.add_argument("--report-every", type=int, default=25)
    parser.add_argument("--final-refine", action="store_true", help="also time the final refinement at the end")
    parser.add_argument("--no-refine", action="store_true", help="fusion only (no refinement per keyframe)")
    args = parser.parse_args(argv)
    recorder = Recorder("map_size", argv)

    config = SlamConfig.preset("rgbd", mapping={"refine_iterations": 0} if args.no_refine else {})
    torch.set_num_threads(config.num_threads)
    timings = StageTimes()
    backend = MappingStage(config.mapping, threaded=False, max_backlog=1, timings=timings)
    if args.cap is not None:
        backend.map.config.voxel_cap = args.cap
    source = open_source(f"synthetic://seed={args.seed}?frames={args.frames or args.keyframes * args.every}")
    K = source.intrinsics.matrix()
    rows, merge, refine = [], [], []
    keyframes = 0
    for frame in source:
        if frame.index % args.every:
            continue
        image = torch.from_numpy(frame.image).float() / 255.0
        depth = torch.from_numpy(frame.depth)
        before = dict(timings.seconds)
        backend.submit(KeyframeJob(frame.index, frame.gt_pose, K, image, grid_from_depth(image, depth, K), depth))
        merge.append(1000 * (timings.seconds["map_merge"] - before["map_merge"]))
        refine.append(1000 * (timings.seconds["map_refine"] - before["map_refine"]))
        keyframes += 1
        if keyframes % args.report_every == 0 or keyframes == args.keyframes:
            recent = slice(-min(10, len(merge)), None)
            row = {"keyframes": keyframes, "surfels": backend.num_gaussians(),
                   "merge_ms": round(sum(merge[recent]) / len(merge[recent]), 1),
                   "refine_ms": round(sum(refine[recent]) / len(refine[recent]), 1), "rss_mb": round(_rss_mb())}
            rows.append(row)
            print(json.dumps(row), flush=True)
        if keyframes == args.keyframes:
            break
    result = {"cap": backend.map.config.voxel_cap, "rows": rows,
              "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}
    if args.final_refine:
        start = time.perf_counter()
        backend.refine_all(config.mapping.final_refine_passes)
        result["final_refine_s"] = round(time.perf_counter() - start, 1)
    print(json.dumps(result))
    # no scoreboard area shows the map size: a record of its own kind, the last report's figures
    last = rows[-1] if rows else {}
    values = {"keyframes": last.get("keyframes", keyframes), "surfels": last.get("surfels"),
              "merge_ms": last.get("merge_ms"), "refine_ms": last.get("refine_ms"), "rss_mib": last.get("rss_mb"),
              "rss_peak_mib": result["peak_rss_mb"]}
    if "final_refine_s" in result:
        values["final_refine_s"] = result["final_refine_s"]
    length = f", path {args.frames} frames" if args.frames else ""
    recorder.write({"sequence": f"synthetic seed {args.seed}", "mode": "rgbd mapping, fusion only" if args.no_refine
                    else "rgbd mapping", "size": f"{args.keyframes} keyframes every {args.every}{length}",
                    "variant": f"voxel cap {result['cap']}"}, values, rows=rows)
    return 0
