"""Synthetic pose graphs with a known answer: a looping ground-truth trajectory, drifting odometry, loop edges.

Used by the pose-graph tests and `bench/pose_graph.py`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worker.geometry import make_sim3, relative_transform, so3_exp, umeyama

from .pose_graph import Sim3PoseGraph


@dataclass
class SyntheticLoopProblem:
    """Ground-truth poses, the odometry-chained (drifted) poses, and the graph built from them."""

    gt_poses: np.ndarray  # [N, 4, 4] SE(3) c2w
    drifted_poses: np.ndarray  # [N, 4, 4] Sim(3) from chaining the drifting odometry
    graph: Sim3PoseGraph
    loop_pairs: list[tuple[int, int]]


def looping_trajectory(n: int, laps: float = 1.0, radius: float = 3.0, rng: np.random.Generator | None = None
                       ) -> np.ndarray:
    """n camera-to-world poses on a wobbling circle, looking outwards; `laps` > 1 revisits the start."""
    rng = rng or np.random.default_rng(0)
    angles = np.linspace(0.0, 2 * np.pi * laps, n, endpoint=False)
    poses = np.zeros((n, 4, 4))
    for k, a in enumerate(angles):
        yaw = torch.tensor([0.0, -a, 0.0], dtype=torch.float64)
        wobble = torch.from_numpy(rng.normal(0.0, 0.02, 3))
        R = (so3_exp(yaw) @ so3_exp(wobble)).numpy()
        t = np.array([radius * np.cos(a), 0.2 * np.sin(3 * a), radius * np.sin(a)])
        poses[k] = make_sim3(torch.from_numpy(R), torch.from_numpy(t)).numpy()
    return poses


def _drift(rng: np.random.Generator, rot_bias: np.ndarray, trans_sigma: float, rot_sigma: float,
           scale_drift: float) -> torch.Tensor:
    omega = torch.from_numpy(rot_bias + rng.normal(0.0, rot_sigma, 3))
    t = torch.from_numpy(rng.normal(0.0, trans_sigma, 3))
    return make_sim3(so3_exp(omega), t, 1.0 + scale_drift)


def make_loop_problem(
    n: int = 300,
    laps: float = 1.15,
    n_loops: int = 20,
    rot_bias: float = 0.003,
    rot_sigma: float = 0.001,
    trans_sigma: float = 0.003,
    scale_drift: float = 0.002,
    submap_length: int = 8,
    seed: int = 0,
    **graph_kwargs,
) -> SyntheticLoopProblem:
    """A looping trajectory of n keyframes, odometry with rotation bias, translation noise and per-step scale drift,
    and `n_loops` correct loop edges between poses of the second lap and the matching poses of the first."""
    rng = np.random.default_rng(seed)
    gt = looping_trajectory(n, laps, rng=rng)
    gt_t = torch.from_numpy(gt)
    bias = np.array([0.3, 1.0, -0.5]) * rot_bias
    drifted = [gt_t[0]]
    graph = Sim3PoseGraph(**graph_kwargs)
    graph.add_node(0, gt_t[0])
    for k in range(1, n):
        rel = relative_transform(gt_t[k - 1], gt_t[k]) @ _drift(rng, bias, trans_sigma, rot_sigma, scale_drift)
        drifted.append(drifted[-1] @ rel)
        graph.add_node(k, drifted[-1])
        graph.add_edge(k - 1, k, rel, "inter_submap" if k % (submap_length - 1) == 0 else "sequential")
    per_lap = int(round(n / laps))
    candidates = np.arange(per_lap, n)
    chosen = rng.choice(candidates, size=min(n_loops, len(candidates)), replace=False) if n_loops else []
    pairs = []
    for j in sorted(int(c) for c in chosen):
        i = j - per_lap
        graph.add_edge(i, j, relative_transform(gt_t[i], gt_t[j]), "loop")
        pairs.append((i, j))
    return SyntheticLoopProblem(gt, torch.stack(drifted).numpy(), graph, pairs)


def shrinking_odometry(truth: list[np.ndarray], shrink: float) -> list[np.ndarray]:
    """A monocular odometry's keyframe poses along `truth` (camera-to-world): the true rotations, each step `shrink`
    times shorter than the one before (its unit drifts), starting at the first true pose."""
    out = [np.asarray(truth[0], np.float64).copy()]
    for k in range(1, len(truth)):
        step = np.linalg.inv(truth[k - 1]) @ truth[k]
        step[:3, 3] *= shrink ** k
        out.append(out[-1] @ step)
    return out


def ate_rmse(estimated: np.ndarray, ground_truth: np.ndarray) -> float:
    """Absolute trajectory error (RMSE of camera centres) after Sim(3) Umeyama alignment."""
    est = torch.from_numpy(np.asarray(estimated, np.float64)[:, :3, 3])
    gt = torch.from_numpy(np.asarray(ground_truth, np.float64)[:, :3, 3])
    s, R, t = umeyama(est, gt, with_scale=True)
    aligned = s * est @ R.T + t
    return float(((aligned - gt) ** 2).sum(-1).mean().sqrt())
