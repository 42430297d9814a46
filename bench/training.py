"""The trained frontend against trajectory baselines, in one run (issue 6's table).

`python -m bench training -- --checkpoints A.safetensors [B ...] [--untrained] [--synthetic 10] [--frames 24]
[--icl DIR ...] [--threads 2] [--json OUT]`

Data: held-out synthetic scenes (seeds 10000.., never used for training; the first `--frames` frames of a 64-frame
loop at 224x160) and ICL living room (every 2nd frame of tests/data/icl_mini, and every 6th of
/work/shared/data/icl_livingroom1_micro when present: both ~36 frames), fitted to 224x160. Methods: identity
poses, constant velocity from the first two ground-truth poses, and each checkpoint run through the SubmapTracker
(submaps of 8, no backend). Metrics: ATE RMSE after Sim(3) alignment (metres) with poses from the pose head and
from the point-map fit (TrackerConfig.pose_source), depth AbsRel with a per-frame median scale, and the PSNR of
each frame's raw per-pixel surfels (no refinement) rendered from its own camera ("own view") and from the next
frame's ground-truth camera against the next image ("next view", surfels scaled to metres by the median depth
ratio). Prints a markdown table of means per dataset.
"""

from __future__ import annotations

import os

# Spinning OpenMP workers make multi-threaded torch many times slower on a shared, oversubscribed machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from dataclasses import asdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

SHIPPED = Path(__file__).resolve().parents[1] / "worker" / "frontend" / "weights" / "tiny.safetensors"
ICL_DEFAULTS = (("tests/data/icl_mini", 2), ("/work/shared/data/icl_livingroom1_micro", 6))


def record_case(group: str, method: str, args: argparse.Namespace) -> dict:
    """A table row's record case: the shipped weights on the held-out synthetic rooms feed the scoreboard's area
    "training"; other rows (baselines, other checkpoints, ICL) are records without an area."""
    shipped = method.endswith(".safetensors") and Path(method).resolve() == SHIPPED
    mode = "tiny (shipped weights)" if shipped else (Path(method).name if method.endswith(".safetensors") else method)
    synthetic = group == "synthetic (held out)"
    case = {"sequence": "synthetic rooms, held out" if synthetic else group, "mode": mode}
    if synthetic and shipped:
        case = {"area": "training", **case}
    defaults = (("sequences", args.synthetic, 10), ("frames", args.frames, 24), ("first seed", args.first_seed, 10_000))
    settings = [f"{name} {value}" for name, value, default in defaults if value != default] if synthetic else []
    return {**case, "variant": ", ".join(settings)} if settings else case


def _fmt(value: float, digits: int) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    from worker.frontend import build_model
    from worker.frontend.checkpoint import load_checkpoint
    from worker.training.evaluate import dataset_sequence, evaluate_baselines, evaluate_model, held_out_synthetic

    p = argparse.ArgumentParser(prog="python -m bench training", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoints", type=Path, nargs="*", default=[])
    p.add_argument("--untrained", action="store_true", help="also score the randomly initialised tiny model")
    p.add_argument("--synthetic", type=int, default=10, help="held-out synthetic sequences")
    p.add_argument("--frames", type=int, default=24, help="frames per synthetic sequence")
    p.add_argument("--first-seed", type=int, default=10_000,
                   help="first held-out seed (10000-10009: the test scenes; e.g. 10020 for validation scenes)")
    p.add_argument("--icl", nargs="*", help="ICL-format folders (default: icl_mini and the shared micro set)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", type=Path, help="write every per-sequence score here")
    args = p.parse_args(argv)
    from bench.record import Recorder

    recorder = Recorder("training", argv)
    torch.set_num_threads(args.threads)

    started = time.perf_counter()
    groups: dict[str, list] = {}
    if args.synthetic:
        groups["synthetic (held out)"] = held_out_synthetic(args.synthetic, args.frames, first_seed=args.first_seed)
    icl = [(path, 1) for path in args.icl] if args.icl is not None else [
        (path, stride) for path, stride in ICL_DEFAULTS if Path(path).is_dir()]
    for path, stride in icl:
        seq = dataset_sequence(path, stride=stride)
        groups[f"ICL {seq.name} ({len(seq.images)} fr.)"] = [seq]
    print(f"data ready in {time.perf_counter() - started:.0f} s: "
          + ", ".join(f"{k}: {len(v)}" for k, v in groups.items()), flush=True)

    models = [(str(path), lambda path=path: load_checkpoint(path)) for path in args.checkpoints]
    if args.untrained:
        models.insert(0, ("untrained", lambda: build_model("tiny").eval()))
    scores = []
    for seqs in groups.values():
        for seq in seqs:
            scores += evaluate_baselines(seq)
    for name, load in models:
        model = load()
        t0 = time.perf_counter()
        for group, seqs in groups.items():
            for seq in seqs:
                scores.append(evaluate_model(model, seq, method=name))
            print(f"  {name} on {group}: {time.perf_counter() - t0:.0f} s", flush=True)

    group_of = {seq.name: group for group, seqs in groups.items() for seq in seqs}
    table: dict[tuple[str, str], list] = defaultdict(list)
    for s in scores:
        table[(group_of[s.sequence], s.method)].append(s)
    print("\n| data | method | ATE RMSE (m), pose head | ATE RMSE (m), point-map pose | depth AbsRel | "
          "raw PSNR own view (dB) | raw PSNR next view (dB) |")
    print("|---|---|---|---|---|---|---|")
    for (group, method), rows in table.items():
        ate, ate_pm, rel, ps, ps_next = (float(np.mean([getattr(r, k) for r in rows]))
                                         for k in ("ate", "ate_pointmap", "abs_rel", "psnr", "psnr_next"))
        print(f"| {group} | {Path(method).name if method.endswith('.safetensors') else method} | {ate:.3f} | "
              f"{_fmt(ate_pm, 3)} | {_fmt(rel, 3)} | {_fmt(ps, 2)} | {_fmt(ps_next, 2)} |")
        figures = {"ate_m": ate, "ate_pointmap_m": ate_pm, "abs_rel": rel, "psnr_db": ps, "psnr_next_db": ps_next}
        values = {k: None if math.isnan(v) else round(v, 4) for k, v in figures.items()}
        recorder.write(record_case(group, method, args), {**values, "sequences": len(rows)})
    print(f"\ntotal {time.perf_counter() - started:.0f} s")
    if args.json:
        args.json.write_text(json.dumps([asdict(s) | {"group": group_of[s.sequence]} for s in scores], indent=1))
    return 0
