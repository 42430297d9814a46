"""Sim(3) pose-graph optimisation time: 2,000 keyframes, 100 loop edges (target < 0.3 s on the 2-core dev CPU).

Two solves of the same synthetic problem (worker.loop.synthetic): the batch Levenberg-Marquardt solve over the whole
graph (`optimize_full`, the reference), and the incremental one as a session runs it: keyframes arrive one by one and
the graph is optimised after every loop (iSAM2, `optimize`). Reported: time per full solve, per incremental solve
after a loop and per added keyframe (`--per-keyframe`: handed to iSAM2 at once), and how far the incremental poses
end from the full solve's. Times are wall clock and, as the shared machine is loaded, process CPU time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from bench.record import Recorder
from worker.loop.pose_graph import Sim3PoseGraph
from worker.loop.synthetic import SyntheticLoopProblem, ate_rmse, make_loop_problem


def _full_solve(problem: SyntheticLoopProblem, repeats: int) -> float:
    graph = problem.graph
    initial_nodes = dict(graph.nodes)
    builds, totals, cpus, iterations = [], [], [], []
    for _ in range(repeats):
        graph.nodes = dict(initial_nodes)
        t0 = time.perf_counter()
        graph.build()
        t1, c1 = time.perf_counter(), time.process_time()
        result = graph.optimize_full(update=False)
        t2, c2 = time.perf_counter(), time.process_time()
        builds.append(t1 - t0)
        totals.append(t2 - t1)
        cpus.append(c2 - c1)
        iterations.append(result.iterations)
    n = len(problem.gt_poses)
    est = np.stack([result.poses[k] for k in range(n)])
    print(f"graph build (factors+values): median {np.median(builds) * 1e3:.1f} ms")
    print(f"optimize_full() incl. build, LM {iterations[-1]} iterations: median {np.median(totals) * 1e3:.1f} ms, "
          f"min {np.min(totals) * 1e3:.1f} ms, CPU median {np.median(cpus) * 1e3:.1f} ms (target < 300 ms)")
    before, after = ate_rmse(problem.drifted_poses, problem.gt_poses), ate_rmse(est, problem.gt_poses)
    print(f"ATE before {before:.3f}  after {after:.4f} (map units, Sim(3)-aligned)")
    return float(np.median(totals)) * 1e3


def _incremental_solve(problem: SyntheticLoopProblem, per_keyframe: bool, threshold: float) -> float:
    """Replay the problem as a session: nodes initialised from the current estimate, optimize after each loop."""
    source = problem.graph
    loops_at: dict[int, list] = {}
    for edge in source.edges_of_kind("loop"):
        loops_at.setdefault(edge.j, []).append(edge)
    graph = Sim3PoseGraph(relinearize_threshold=threshold)
    graph.add_node(0, source.nodes[0])
    loop_times: list[tuple[int, float, float, int]] = []  # (keyframe, seconds, CPU seconds, iSAM2 updates)
    keyframe_times: list[tuple[float, float]] = []  # (seconds, CPU seconds) once iSAM2 runs
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for edge in (e for e in source.edges if e.kind != "loop"):
        t0, c0 = time.perf_counter(), time.process_time()
        graph.add_node(edge.j, graph.nodes[edge.i] @ edge.relative)
        graph.add_edge(edge.i, edge.j, edge.relative, edge.kind)
        if edge.j in loops_at:
            for loop in loops_at[edge.j]:
                graph.add_edge(loop.i, loop.j, loop.relative, "loop")
            result = graph.optimize()
            loop_times.append((edge.j, time.perf_counter() - t0, time.process_time() - c0, result.iterations))
        elif (graph.flush() if per_keyframe else loop_times):
            keyframe_times.append((time.perf_counter() - t0, time.process_time() - c0))
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    final = graph.optimize()
    reference = Sim3PoseGraph()
    reference.load_state_dict(graph.state_dict())
    full = reference.optimize_full()
    n = len(problem.gt_poses)
    diff = max(float(np.abs(final.poses[k][:3, 3] - full.poses[k][:3, 3]).max()) for k in range(n))
    times = np.array([t for _, t, _, _ in loop_times])
    cpu_times = np.array([c for _, _, c, _ in loop_times])
    print(f"incremental (iSAM2, relinearize threshold {threshold}): {len(loop_times)} loop solves (the first one "
          f"batch), per loop median {np.median(times) * 1e3:.1f} ms, p95 {np.percentile(times, 95) * 1e3:.1f} ms, "
          f"max {times.max() * 1e3:.1f} ms; CPU median {np.median(cpu_times) * 1e3:.1f} ms, last 50 loops "
          f"{np.median(cpu_times[-50:]) * 1e3:.1f} ms; median {int(np.median([u for *_, u in loop_times]))} "
          f"iSAM2 updates")
    kt = np.array(keyframe_times).reshape(-1, 2)
    what = "add_node + add_edge + flush (one iSAM2 update)" if per_keyframe else "add_node + add_edge"
    print(f"per keyframe without a loop after the first solve ({len(kt)}), {what}: median "
          f"{np.median(kt[:, 0]) * 1e3:.2f} ms, CPU median {np.median(kt[:, 1]) * 1e3:.2f} ms, CPU last 100 "
          f"{np.median(kt[-100:, 1]) * 1e3:.2f} ms")
    print(f"whole incremental replay: {wall:.1f} s wall, {cpu:.1f} s CPU")
    est = np.stack([final.poses[k] for k in range(n)])
    full_est = np.stack([full.poses[k] for k in range(n)])
    print(f"incremental vs full solve of the final graph: max position difference {diff:.2e}, cost "
          f"{final.final_error:.3f} vs {full.final_error:.3f}, ATE {ate_rmse(est, problem.gt_poses):.4f} vs "
          f"{ate_rmse(full_est, problem.gt_poses):.4f}")
    return float(np.median(times)) * 1e3


def record_cases(keyframes: int, loops: int, per_keyframe: bool, threshold: float | None) -> tuple[dict, dict]:
    """The records' cases (area "loop"): the full solve, and the incremental solve after a loop as the scoreboard
    names it for `--per-keyframe` at the default threshold (other settings say so in `mode`)."""
    sequence = f"{keyframes:,} keyframes, {loops:,} loops"
    incremental = "pose graph, incremental after a loop"
    settings = ([] if per_keyframe else ["iSAM2 at loops only"]) + (
        [] if threshold is None else [f"relinearize threshold {threshold:g}"])
    if settings:
        incremental += f" ({', '.join(settings)})"
    return ({"area": "loop", "sequence": sequence, "mode": "pose graph, full solve"},
            {"area": "loop", "sequence": sequence, "mode": incremental})


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench pose_graph")
    parser.add_argument("--keyframes", type=int, default=2000)
    parser.add_argument("--loops", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--per-keyframe", action="store_true",
                        help="hand every keyframe to iSAM2 as it comes (flush), not only at the next loop")
    parser.add_argument("--threshold", type=float, default=None, help="iSAM2 relinearize threshold")
    args = parser.parse_args(argv)
    recorder = Recorder("pose_graph", argv)
    torch.set_num_threads(2)
    # Drift per keyframe chosen so the whole run drifts by about 1 rad in heading and 1.8x in scale.
    problem = make_loop_problem(n=args.keyframes, laps=1.3, n_loops=args.loops, rot_bias=0.0005, rot_sigma=0.0005,
                                trans_sigma=0.003, scale_drift=0.0003)
    print(f"keyframes={len(problem.gt_poses)} loop_edges={len(problem.loop_pairs)} edges={len(problem.graph.edges)}")
    full_ms = _full_solve(problem, args.repeats)
    threshold = Sim3PoseGraph().relinearize_threshold if args.threshold is None else args.threshold
    incremental_ms = _incremental_solve(problem, args.per_keyframe, threshold)
    full_case, incremental_case = record_cases(len(problem.gt_poses), len(problem.loop_pairs), args.per_keyframe,
                                               args.threshold)
    recorder.write(full_case, {"latency_ms": round(full_ms, 1)})
    recorder.write(incremental_case, {"latency_ms": round(incremental_ms, 1)})
    return 0
