"""Rasterizer figures: forward and forward+backward time of the compiled CPU path, the pure-torch reference and
(when CUDA and gsplat exist) gsplat, at 320x240 and 640x480 with 50k and 200k surfels built from real ICL frames.

Surfels: pixels of several ICL living-room frames unprojected with their depth and ground-truth pose (one surfel
per sampled pixel, facing its source camera, radius = one source pixel, opacity 0.9, the pixel's colour); the
view rendered is a frame in the middle of those. Backward = gradients of a weighted sum of all four outputs w.r.t.
every surfel attribute and the view matrix. Figures are medians (and minima) over repeats, wall clock, after one
warm-up call. The compiled path runs `--repeats` times, the (seconds-slow) reference `--reference-repeats` times.

`python -m bench render -- [--quick] [--threads N] [--repeats N] [--reference-repeats N] [--no-reference]
[--sizes 320x240,640x480] [--counts 50000,200000] [--device cpu|cuda]`; each row is also printed as a markdown
table row (`| size | surfels | backend | fwd ms | fwd+bwd ms | CPU ms fwd / fwd+bwd | notes |`) for
bench/RESULTS.md. Wall times are medians (minima); CPU time is the process's, all threads, median.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from bench.record import Recorder

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIRS = (Path("/work/shared/data/icl_livingroom1_micro"), REPO_ROOT / "tests" / "data" / "icl_mini")
SIZES = ((320, 240), (640, 480))
COUNTS = (50_000, 200_000)
REFERENCE_MAX_PAIRS = 50_000 * 640 * 480  # skip the reference above this (surfels x pixels): minutes and GBs


def load_frames(n_frames: int = 12):
    from worker.data.sources import open_source

    root = next(d for d in DATA_DIRS if d.is_dir())
    source = open_source(root, use_gt_poses=True)
    frames = list(source)
    stride = max(1, len(frames) // (3 * n_frames))
    return root, frames[: n_frames * stride: stride]


def surfels_from_frames(frames, count: int, seed: int = 0):
    """`count` surfels sampled uniformly from the valid-depth pixels of `frames` (world frame)."""
    from worker.geometry import rotmat_to_quat, unproject_depth
    from worker.mapping import Surfels

    gen = torch.Generator().manual_seed(seed)
    means, quats, scales, colors = [], [], [], []
    per_frame = -(-count // len(frames))
    for frame in frames:
        K = frame.intrinsics.matrix(torch.float64)
        depth = torch.from_numpy(frame.depth.astype(np.float64))
        valid = (depth > 0).flatten().nonzero()[:, 0]
        pick = valid[torch.randperm(valid.numel(), generator=gen)[:per_frame]]
        pts = unproject_depth(depth, K).reshape(-1, 3)[pick]
        c2w = torch.from_numpy(np.asarray(frame.gt_pose, dtype=np.float64))
        means.append(pts @ c2w[:3, :3].T + c2w[:3, 3])
        quats.append(rotmat_to_quat(c2w[:3, :3]).expand(pick.numel(), 4))
        radius = depth.flatten()[pick] / K[0, 0]
        scales.append(torch.stack([radius, radius], -1))
        colors.append(torch.from_numpy(frame.image.reshape(-1, 3)[pick.numpy()].astype(np.float64) / 255.0))
    n = sum(m.shape[0] for m in means)
    surfels = Surfels(torch.cat(means), torch.cat(quats), torch.cat(scales), torch.full((n,), 0.9),
                      torch.cat(colors), torch.zeros(n, dtype=torch.int64))
    return surfels.select(torch.arange(min(count, n))).to(dtype=torch.float32)


def view_of(frame, width: int, height: int):
    from worker.geometry import sim3_inverse

    K = frame.intrinsics.scaled(width, height).matrix(torch.float32)
    viewmat = sim3_inverse(torch.from_numpy(np.asarray(frame.gt_pose, dtype=np.float64))).to(torch.float32)
    return viewmat, K


def time_call(fn, repeats: int, sync) -> tuple[float, float, float]:
    """(median wall ms, min wall ms, median process CPU ms) per call.

    The CPU time (all threads of this process) is the cost itself, nearly unaffected by other processes on a shared
    machine; wall time on a busy machine is not.
    """
    fn()  # warm-up (and the one-off compile of the CPU kernels)
    sync()
    times, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        sync()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(times) * 1e3, min(times) * 1e3, statistics.median(cpu) * 1e3


def bench_backend(surfels, viewmat, K, width, height, backend: str, repeats: int, device: str) -> dict:
    from worker.mapping import rasterize

    surfels = surfels.to(device)
    viewmat, K = viewmat.to(device), K.to(device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    gen = torch.Generator().manual_seed(1)
    weights = [torch.rand(s, generator=gen).to(device) for s in
               ((height, width, 3), (height, width), (height, width), (height, width, 3))]

    def forward():
        with torch.no_grad():
            return rasterize(surfels, viewmat, K, width, height, backend=backend)

    leaves = [t.detach().clone().requires_grad_(True) for t in
              (surfels.means, surfels.quats, surfels.scales, surfels.opacities, surfels.colors)]
    V = viewmat.detach().clone().requires_grad_(True)

    def forward_backward():
        from worker.mapping import Surfels

        for t in (*leaves, V):
            t.grad = None
        s = Surfels(*leaves, keyframe_ids=surfels.keyframe_ids)
        out = rasterize(s, V, K, width, height, backend=backend)
        sum((w * o).sum() for w, o in zip(weights, out)).backward()

    fwd, fwd_min, fwd_cpu = time_call(forward, repeats, sync)
    fb, fb_min, fb_cpu = time_call(forward_backward, repeats, sync)
    coverage = forward().alpha.mean().item()
    return {"fwd": fwd, "fwd_min": fwd_min, "fwd_cpu": fwd_cpu, "fb": fb, "fb_min": fb_min, "fb_cpu": fb_cpu,
            "coverage": coverage}


def _sizes(text: str) -> tuple[tuple[int, int], ...]:
    try:
        return tuple((int(w), int(h)) for w, h in (item.lower().split("x") for item in text.split(",")))
    except ValueError:
        raise argparse.ArgumentTypeError(f"sizes must look like 320x240,640x480, got {text!r}") from None


def _counts(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(c) for c in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"counts must look like 50000,200000, got {text!r}") from None


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{cpu}, {os.cpu_count()} logical CPUs, torch {torch.__version__}, {torch.get_num_threads()} threads, "
            f"load average {load:.1f} at start")


def record_case(width: int, height: int, count: int, backend: str, threads: int) -> dict:
    """A row's record case (area "rasterizer"), named as the scoreboard's rows are."""
    cores = f"{threads} thread{'s' if threads != 1 else ''}"
    mode = {"cpu": f"CPU, {cores}", "reference": f"pure-torch reference, CPU, {cores}",
            "gsplat": "GPU (gsplat)"}.get(backend, backend)
    return {"area": "rasterizer", "sequence": f"{width}x{height}, {count / 1000:g}k surfels", "mode": mode}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench render", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="320x240 / 50k only, 3 repeats")
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--reference-repeats", type=int, default=2)
    parser.add_argument("--no-reference", action="store_true")
    parser.add_argument("--sizes", type=_sizes, default=SIZES, help="comma-separated WxH list")
    parser.add_argument("--counts", type=_counts, default=COUNTS, help="comma-separated surfel counts")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args(argv)
    recorder = Recorder("render", argv)
    torch.set_num_threads(args.threads)
    sizes, counts, repeats = (SIZES[:1], COUNTS[:1], 3) if args.quick else (args.sizes, args.counts, args.repeats)

    from worker.mapping import raster_cpu, raster_gsplat

    root, frames = load_frames()
    print(f"machine: {machine()}")
    print(f"data: {root} ({len(frames)} frames), compiled CPU path available: {raster_cpu.available()}")
    backends = ["cpu"] + ([] if args.no_reference else ["reference"])
    if args.device == "cuda" and raster_gsplat.available():
        backends.append("gsplat")
    view = frames[len(frames) // 2]
    header = (f"{'size':>9} {'surfels':>8} {'backend':>9} {'fwd ms (min)':>16} {'fwd+bwd ms (min)':>18} "
              f"{'CPU ms fwd / fwd+bwd':>21} {'alpha':>6}")
    print(header)
    markdown = []
    for count in counts:
        surfels = surfels_from_frames(frames, count)
        for width, height in sizes:
            viewmat, K = view_of(view, width, height)
            results = {}
            for backend in backends:
                if backend == "reference" and count * width * height > REFERENCE_MAX_PAIRS:
                    print(f"{width}x{height:<4} {count:>8} {backend:>9}  skipped (too slow / too much memory)")
                    continue
                device = "cuda" if backend == "gsplat" else "cpu"
                n = args.reference_repeats if backend == "reference" else repeats
                r = bench_backend(surfels, viewmat, K, width, height, backend, n, device)
                results[backend] = r
                recorder.write(record_case(width, height, count, backend, args.threads),
                               {"fwd_ms": round(r["fwd"], 2), "fwd_bwd_ms": round(r["fb"], 2),
                                "fwd_min_ms": round(r["fwd_min"], 2), "fwd_bwd_min_ms": round(r["fb_min"], 2),
                                "fwd_cpu_ms": round(r["fwd_cpu"], 2), "fwd_bwd_cpu_ms": round(r["fb_cpu"], 2),
                                "alpha_mean": round(r["coverage"], 4), "repeats": n})
                print(f"{width}x{height:<4} {count:>8} {backend:>9} {r['fwd']:>8.1f} ({r['fwd_min']:.1f}) "
                      f"{r['fb']:>9.1f} ({r['fb_min']:.1f}) {r['fwd_cpu']:>10.1f} / {r['fb_cpu']:.1f} "
                      f"{r['coverage']:>6.3f}", flush=True)
                markdown.append(f"| {width}x{height} | {count // 1000}k | {backend} | {r['fwd']:.1f} "
                                f"({r['fwd_min']:.1f}) | {r['fb']:.1f} ({r['fb_min']:.1f}) | {r['fwd_cpu']:.1f} / "
                                f"{r['fb_cpu']:.1f} | {args.threads} threads, {n} repeats |")
            if "reference" in results:
                ref, cpu = results["reference"], results["cpu"]
                wall = (ref["fwd"] / cpu["fwd"], ref["fb"] / cpu["fb"])
                work = (ref["fwd_cpu"] / cpu["fwd_cpu"], ref["fb_cpu"] / cpu["fb_cpu"])
                print(f"{'':>28} speed-up vs reference: fwd {wall[0]:.0f}x, fwd+bwd {wall[1]:.0f}x (wall); "
                      f"{work[0]:.0f}x, {work[1]:.0f}x (CPU time)")
                markdown[-1] = (markdown[-1][:-2] + f"; compiled path {wall[0]:.0f}x / {wall[1]:.0f}x faster (wall), "
                                f"{work[0]:.0f}x / {work[1]:.0f}x (CPU time) |")
    print("\n".join(markdown))
    return 0
