"""Frame sources, synthetic rendering and metric costs: `python -m bench data_eval`."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from worker.data import open_source
from worker.data.synthetic import make_sequence
from worker.eval import absolute_trajectory_error, psnr, ssim

ICL_MINI = Path(__file__).resolve().parents[1] / "tests" / "data" / "icl_mini"


def timed(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds of fn()."""
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return float(np.median(walls) * 1e3), float(np.median(cpus) * 1e3)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench data_eval")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    print(f"{'what':44s} {'wall ms':>9s} {'cpu ms':>9s}")
    for width, height in ((160, 120), (320, 240), (640, 480)):
        seq = make_sequence(10_000, num_frames=args.repeats, width=width, height=height)
        counter = iter(range(10**9))
        wall, cpu = timed(lambda seq=seq, counter=counter: seq.frame(next(counter) % len(seq)), args.repeats)
        print(f"{f'synthetic render {width}x{height}':44s} {wall:9.1f} {cpu:9.1f}")
    if ICL_MINI.is_dir():
        source = open_source(ICL_MINI)
        start, cpu0 = time.perf_counter(), time.process_time()
        count = sum(1 for _ in source)
        wall, cpu = (time.perf_counter() - start) * 1e3 / count, (time.process_time() - cpu0) * 1e3 / count
        print(f"{'ICL read 320x240 rgb+depth (per frame)':44s} {wall:9.1f} {cpu:9.1f}")
    rng = np.random.default_rng(0)
    ref = np.cumsum(rng.normal(0, 0.05, (10_000, 3)), axis=0)
    est = 0.5 * ref + rng.normal(0, 0.01, ref.shape)
    wall, cpu = timed(lambda: absolute_trajectory_error(est, ref, "sim3"), 5)
    print(f"{'ATE Sim(3), 10k poses':44s} {wall:9.1f} {cpu:9.1f}")
    a = rng.uniform(0, 1, (480, 640, 3))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    wall, cpu = timed(lambda: psnr(a, b), 5)
    print(f"{'PSNR 640x480':44s} {wall:9.1f} {cpu:9.1f}")
    wall, cpu = timed(lambda: ssim(a, b), 5)
    print(f"{'SSIM 640x480':44s} {wall:9.1f} {cpu:9.1f}")
    return 0
