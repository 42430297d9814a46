"""Sim(3) pose-graph optimisation time: 2,000 keyframes, 100 loop edges (target < 0.3 s on the 2-core dev CPU)."""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from worker.loop.synthetic import ate_rmse, make_loop_problem


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench pose_graph")
    parser.add_argument("--keyframes", type=int, default=2000)
    parser.add_argument("--loops", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    # Drift per keyframe chosen so the whole run drifts by about 1 rad in heading and 1.8x in scale.
    problem = make_loop_problem(n=args.keyframes, laps=1.3, n_loops=args.loops, rot_bias=0.0005, rot_sigma=0.0005,
                                trans_sigma=0.003, scale_drift=0.0003)
    graph = problem.graph
    n = len(problem.gt_poses)
    initial_nodes = dict(graph.nodes)
    builds, totals, iterations = [], [], []
    for _ in range(args.repeats):
        graph.nodes = dict(initial_nodes)
        t0 = time.perf_counter()
        graph.build()
        t1 = time.perf_counter()
        result = graph.optimize(update=False)
        t2 = time.perf_counter()
        builds.append(t1 - t0)
        totals.append(t2 - t1)
        iterations.append(result.iterations)
    est = np.stack([result.poses[k] for k in range(n)])
    print(f"keyframes={n} loop_edges={len(problem.loop_pairs)} edges={len(graph.edges)}")
    print(f"graph build (factors+values): median {np.median(builds) * 1e3:.1f} ms")
    print(f"optimize() incl. build, LM {iterations[-1]} iterations: median {np.median(totals) * 1e3:.1f} ms, "
          f"min {np.min(totals) * 1e3:.1f} ms (target < 300 ms)")
    before, after = ate_rmse(problem.drifted_poses, problem.gt_poses), ate_rmse(est, problem.gt_poses)
    print(f"ATE before {before:.3f}  after {after:.4f} (map units, Sim(3)-aligned)")
    return 0
