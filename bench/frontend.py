"""Frontend model latency: ms per `step` (batch 1, inference mode) on CPU, and on GPU when CUDA is present.

`python -m bench frontend [--configs tiny,small,base] [--threads 1,2] [--iters 20] [--paper]`
CPU: each config at 224x160 (a 224-wide 4:3 frame) and at its own long side. GPU (if present): the paper model at
512x384 in fp32 eager, bf16 eager and bf16 + CUDA graphs. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from bench.record import Recorder
from worker.frontend import build_model, get_config, parameter_tally


def _time_steps(step, image, state, iters: int, warmup: int = 3, sync=lambda: None):
    """Wall-clock and process-CPU milliseconds of each step (CPU time is the fairer figure on a shared machine
    when running 1 thread: it does not count time the process spent waiting for a core)."""
    for _ in range(warmup):
        state = step(image, state).state
    sync()
    wall, cpu = [], []
    for _ in range(iters):
        start, start_cpu = time.perf_counter(), time.process_time()
        out = step(image, state)
        sync()
        wall.append((time.perf_counter() - start) * 1000.0)
        cpu.append((time.process_time() - start_cpu) * 1000.0)
        state = out.state
    return wall, cpu


def _row(label: str, size: tuple[int, int], timings) -> str:
    wall, cpu = timings
    return (f"| {label} | {size[1]}x{size[0]} | {statistics.median(wall):.1f} | {min(wall):.1f} | "
            f"{statistics.median(cpu):.1f} | {len(wall)} |")


def _record(recorder: Recorder | None, mode: str, size: tuple[int, int], timings) -> None:
    """A record (area "frontend") of one row: the median wall time per frame, as the scoreboard shows it."""
    if recorder is None:
        return
    wall, cpu = timings
    recorder.write({"area": "frontend", "sequence": f"{size[1]}x{size[0]}", "mode": mode},
                   {"latency_ms": round(statistics.median(wall), 1), "latency_min_ms": round(min(wall), 1),
                    "cpu_ms": round(statistics.median(cpu), 1), "frames": len(wall)})


def bench_cpu(configs: list[str], threads: list[int], iters: int, recorder: Recorder | None = None) -> list[str]:
    rows = []
    for name in configs:
        model = build_model(name)
        params = parameter_tally(model)["total"] / 1e6
        long_side = get_config(name).image_long_side
        sizes = [(160, 224)] + ([(long_side * 3 // 4, long_side)] if long_side != 224 else [])
        for n_threads in threads:
            torch.set_num_threads(n_threads)
            for h, w in sizes:
                image = torch.rand(1, 3, h, w)
                with torch.inference_mode():
                    times = _time_steps(model.step, image, model.init_state(), iters)
                rows.append(_row(f"{name} ({params:.1f} M), CPU fp32, {n_threads} thread(s)", (h, w), times))
                _record(recorder, f"{name}, CPU fp32, {n_threads} thread{'s' if n_threads > 1 else ''}", (h, w), times)
                print(rows[-1], flush=True)
    return rows


def bench_gpu(iters: int, recorder: Recorder | None = None) -> list[str]:
    rows = []
    model = build_model("paper", device="cuda")
    image = torch.rand(1, 3, 384, 512, device="cuda")
    sync = torch.cuda.synchronize
    for precision in ("fp32", "bf16"):
        model.set_precision(precision)
        with torch.inference_mode():
            times = _time_steps(model.step, image, model.init_state(), iters, sync=sync)
        rows.append(_row(f"paper, GPU {precision} eager", (384, 512), times))
        _record(recorder, f"paper size, GPU {precision} eager", (384, 512), times)
        print(rows[-1], flush=True)
    stepper = model.compile_step(384, 512, precision="bf16")
    times = _time_steps(stepper.step, image, model.init_state(), iters, sync=sync)
    rows.append(_row("paper, GPU bf16 + CUDA graphs", (384, 512), times))
    _record(recorder, "paper size, GPU bf16 + CUDA graphs", (384, 512), times)
    print(rows[-1], flush=True)
    return rows


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench frontend")
    parser.add_argument("--configs", default="tiny,small,base")
    parser.add_argument("--threads", default="2,1")
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--paper", action="store_true", help="also time the paper model on CPU (slow, 3 GB)")
    args = parser.parse_args(argv)
    recorder = Recorder("frontend", argv)
    configs = [c for c in args.configs.split(",") if c] + (["paper"] if args.paper else [])
    print("| model, device | frame (WxH) | median wall ms/frame | min wall ms | median process-CPU ms | frames |")
    print("|---|---|---|---|---|---|")
    bench_cpu(configs, [int(t) for t in args.threads.split(",")], args.iters, recorder)
    if torch.cuda.is_available():
        bench_gpu(args.iters, recorder)
    else:
        print("(no CUDA device: GPU rows skipped)")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
