"""Map refinement benchmark: fuse ICL keyframes into a GaussianMap at 320x240, time fusion and 20 refinement steps.

Keyframes come from tests/data/icl_mini (ground-truth poses and depth; surfels from the depth, one per pixel,
then adaptive voxelization), so the map is realistic in size and overlap. Reports per keyframe: surfels before and
after voxelization, add_keyframe (prune + fuse) time, refine(20) time over the last K keyframes, and the newest
keyframe's PSNR before and after refinement. Usage: python -m bench refine (defaults) or
python -m bench.refine [--keyframes 6] [--stride 4] [--iterations 20] [--window 5] [--final 0]

With `--final N`, the end-of-run pass (`GaussianMap.refine_global`, N iterations, no time bound, the engine's
learning-rate decay to 0.3) follows, and its time and the keyframes' mean PSNR before and after are reported.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from bench.record import Recorder

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "icl_mini"


def _load_keyframes(count: int, stride: int) -> list[dict]:
    from worker.geometry import sim3_from_quat

    intr = json.loads((DATA / "intrinsics.json").read_text())
    K = torch.tensor([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]], dtype=torch.float32)
    poses = {}
    for line in (DATA / "groundtruth.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        t, tx, ty, tz, qx, qy, qz, qw = map(float, line.split())
        poses[round(t * 30)] = sim3_from_quat(torch.tensor([qw, qx, qy, qz], dtype=torch.float64),
                                              torch.tensor([tx, ty, tz], dtype=torch.float64))
    names = sorted(p.stem for p in (DATA / "rgb").glob("*.jpg"))[::stride][:count]
    frames = []
    for name in names:
        rgb = cv2.cvtColor(cv2.imread(str(DATA / "rgb" / f"{name}.jpg")), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(DATA / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
        frames.append({
            "id": int(name), "pose": poses[int(name)], "K": K,
            "image": torch.from_numpy(rgb).float() / 255.0,
            "depth": torch.from_numpy(depth / float(intr["depth_scale"])),
        })
    return frames


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench refine")
    parser.add_argument("--keyframes", type=int, default=6)
    parser.add_argument("--stride", type=int, default=4, help="take every n-th frame of icl_mini as a keyframe")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--window", type=int, default=5)
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--device", default="cpu", help="cpu, or cuda (rasterizer: gsplat when it imports)")
    parser.add_argument("--final", type=int, default=0, help="iterations of the end-of-run pass (0: none)")
    args = parser.parse_args(argv)
    recorder = Recorder("refine", argv)
    torch.set_num_threads(args.threads)

    from worker.mapping import GaussianMap, MapConfig, raster_cpu, raster_gsplat, rasterize, voxelize
    from worker.mapping.gaussian_map import rigid_viewmat
    from worker.mapping.losses import psnr
    from worker.pipeline.surfel_init import grid_from_depth

    if args.device == "cuda":
        backend = "gsplat (CUDA)" if raster_gsplat.available() else "pure-torch reference (CUDA)"
    else:
        backend = "compiled cpu" if raster_cpu.available() else "pure-torch reference"
    frames = _load_keyframes(args.keyframes, args.stride)
    gmap = GaussianMap(MapConfig(window=args.window, iterations=args.iterations, device=args.device,
                                 final_refine_budget_s=math.inf, final_refine_lr_end=0.3))
    sync = torch.cuda.synchronize if args.device == "cuda" else (lambda: None)
    rows = []
    for f in frames:
        f = {k: v.to(args.device) if torch.is_tensor(v) and k != "pose" else v for k, v in f.items()}
        g = grid_from_depth(f["image"], f["depth"], f["K"])
        vox = voxelize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], valid=g["valid"],
                       keyframe_id=f["id"], merged_scale_factor=2.0)
        t0 = time.perf_counter()
        stats = gmap.add_keyframe(f["id"], f["pose"], f["K"], f["image"], vox.surfels, depth=f["depth"])
        t_add = time.perf_counter() - t0
        sync()
        viewmat, _ = rigid_viewmat(f["pose"])
        viewmat = viewmat.to(args.device)
        H, W = f["image"].shape[:2]
        with torch.no_grad():
            before = psnr(rasterize(gmap.surfels, viewmat.float(), f["K"], W, H).rgb, f["image"])
        t0, c0 = time.perf_counter(), time.process_time()
        gmap.refine()
        sync()
        t_refine, c_refine = time.perf_counter() - t0, time.process_time() - c0
        with torch.no_grad():
            after = psnr(rasterize(gmap.surfels, viewmat.float(), f["K"], W, H).rgb, f["image"])
        rows.append({"kf": f["id"], "pixels": int(g["valid"].sum()), "voxelized": len(vox.surfels),
                     "pruned": stats.pruned, "added": stats.added, "map": gmap.num_gaussians,
                     "add_s": t_add, "refine_s": t_refine, "refine_cpu_s": c_refine, "psnr_before": before,
                     "psnr_after": after})
        r = rows[-1]
        print(f"kf {r['kf']:3d}: pixels {r['pixels']} -> voxelized {r['voxelized']} | pruned {r['pruned']} "
              f"added {r['added']} map {r['map']} | add_keyframe {t_add:.2f} s | refine({args.iterations}) "
              f"{t_refine:.2f} s wall, {c_refine:.2f} s CPU | PSNR {before:.2f} -> {after:.2f} dB", flush=True)
    steady = rows[1:] or rows
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"rasterizer backend: {backend}; device {args.device}; threads {args.threads}; 320x240; "
          f"load average at the end {load:.1f}")
    print(f"median add_keyframe {statistics.median(r['add_s'] for r in steady):.2f} s, median refine("
          f"{args.iterations}) {statistics.median(r['refine_s'] for r in steady):.2f} s "
          f"({1000 * statistics.median(r['refine_s'] for r in steady) / args.iterations:.0f} ms/iteration wall, "
          f"{1000 * statistics.median(r['refine_cpu_s'] for r in steady) / args.iterations:.0f} ms CPU), "
          f"voxelization keeps {statistics.mean(r['voxelized'] / r['pixels'] for r in rows):.1%} of pixels, "
          f"mean PSNR gain {statistics.mean(r['psnr_after'] - r['psnr_before'] for r in rows):+.2f} dB")
    values = {"keyframe_s": round(statistics.median(r["refine_s"] for r in steady), 3),
              "keyframe_cpu_s": round(statistics.median(r["refine_cpu_s"] for r in steady), 3),
              "add_keyframe_s": round(statistics.median(r["add_s"] for r in steady), 3),
              "psnr_gain_db": round(statistics.mean(r["psnr_after"] - r["psnr_before"] for r in rows), 3)}
    if args.final > 0:
        final_s, before, after = _final_pass(gmap, frames, args.final, args.device, sync)
        values.update({"final_s": round(final_s, 3), "final_psnr_before_db": round(before, 3),
                       "final_psnr_after_db": round(after, 3)})
    H, W = frames[0]["image"].shape[:2] if frames else (240, 320)
    recorder.write(record_case(len(frames), W, H, args, raster_gsplat.available()), values)
    return 0


def record_case(keyframes: int, width: int, height: int, args: argparse.Namespace, gsplat: bool) -> dict:
    """The run's record case (area "refinement"), named as the scoreboard's rows are; settings other than the
    defaults the scoreboard's figures use (20 iterations, window 5, stride 4, the final pass's 200) say so."""
    if args.device == "cuda":
        mode = "GPU (gsplat)" if gsplat else "GPU (pure-torch reference)"
    else:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        mode = f"CPU, {cores} vCPUs" + ("" if args.threads == min(2, os.cpu_count() or 1) else
                                        f", {args.threads} thread{'s' if args.threads != 1 else ''}")
    settings = [f"{name} {value}" for name, value, default in
                (("iterations", args.iterations, 20), ("window", args.window, 5), ("stride", args.stride, 4),
                 ("final", args.final, 200)) if value != default]
    case = {"area": "refinement", "sequence": f"ICL, {keyframes} keyframes {width}x{height}", "mode": mode}
    return {**case, "variant": ", ".join(settings)} if settings else case


def _final_pass(gmap, frames: list[dict], iterations: int, device: str, sync) -> tuple[float, float, float]:
    """Time `refine_global(iterations)` and print the keyframes' mean PSNR before and after it; returns (seconds,
    PSNR before, PSNR after)."""
    from worker.mapping import rasterize
    from worker.mapping.gaussian_map import rigid_viewmat
    from worker.mapping.losses import psnr

    def mean_psnr() -> float:
        scores = []
        with torch.no_grad():
            for f in frames:
                viewmat, _ = rigid_viewmat(f["pose"])
                image = f["image"].to(device)
                H, W = image.shape[:2]
                scores.append(psnr(rasterize(gmap.surfels, viewmat.to(device).float(), f["K"].to(device), W, H).rgb,
                                   image))
        return statistics.mean(scores)

    before = mean_psnr()
    sync()
    t0 = time.perf_counter()
    gmap.refine_global(iterations)
    sync()
    elapsed = time.perf_counter() - t0
    after = mean_psnr()
    print(f"final refinement: {iterations} iterations over {len(frames)} keyframes in {elapsed:.2f} s "
          f"({1000 * elapsed / iterations:.0f} ms/iteration); keyframes' mean PSNR {before:.2f} -> "
          f"{after:.2f} dB", flush=True)
    return elapsed, before, after


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
