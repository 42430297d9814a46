"""The pose graph of a visual-odometry session (`worker.pipeline.assembly.pose_graph(monocular=True)`): its odometry
edges let the scale drift (`loop.monocular_scale_sigma`) and its loops carry their measured uncertainty and a wider
robust kernel, so that loops take out a monocular odometry's scale drift instead of being cut as outliers. On a
constructed trajectory whose odometry shrinks its unit keyframe by keyframe and whose loops are measured with a
few per cent of error, as visual odometry's loops on TUM fr1/xyz are (bench/journal/62)."""

from __future__ import annotations

import numpy as np
import torch

from bench.monocular_graph import DRIFT  # the benchmark's `drift` variant: the same settings
from worker.config import SlamConfig
from worker.geometry import sim3_decompose
from worker.loop.pose_graph import Sim3PoseGraph
from worker.loop.synthetic import ate_rmse, shrinking_odometry
from worker.pipeline.assembly import pose_graph

KEYFRAMES = 40
SHRINK = 0.99  # the odometry's unit shrinks 1 % a keyframe: 32 % over the trajectory


def _truth() -> list[np.ndarray]:
    """Keyframes going back and forth over a desk (camera-to-world), as a hand-held sweep does."""
    poses = []
    for k in range(KEYFRAMES):
        pose = np.eye(4)
        yaw = 0.1 * np.sin(0.3 * k)
        pose[:3, :3] = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        pose[:3, 3] = [0.4 * np.sin(0.3 * k), 0.05 * np.cos(0.2 * k), 0.02 * k]
        poses.append(pose)
    return poses


def _loop_measurement(truth: list[np.ndarray], i: int, j: int, rng: np.random.Generator) -> np.ndarray:
    """T_i^-1 T_j in the odometry's units at keyframe i (its steps are SHRINK^(i+1) of the true ones), with j's
    unit over i's as its scale, off by a few per cent in translation and scale as a loop verified on stereo depth
    is."""
    relative = np.linalg.inv(truth[i]) @ truth[j]
    relative[:3, 3] *= SHRINK ** (i + 1) * (1 + rng.normal(0, 0.03))
    relative[:3, 3] += rng.normal(0, 0.005, 3)
    scale = SHRINK ** -(j - i) * np.exp(rng.normal(0, 0.03))
    relative[:3, :3] *= scale
    return relative


def _solve(graph: Sim3PoseGraph) -> tuple[float, float]:
    """Build the chain, add the loops, optimise; returns (ATE after a similarity alignment, the largest scale
    error along the trajectory) against the truth, both relative."""
    truth = _truth()
    tracked = shrinking_odometry(truth, SHRINK)
    rng = np.random.default_rng(7)
    graph.set_length_unit(1.0)
    for k in range(KEYFRAMES):
        graph.add_node(k, tracked[k])
        if k:
            graph.add_edge(k - 1, k, np.linalg.inv(tracked[k - 1]) @ tracked[k], kind="sequential")
    for i in range(0, KEYFRAMES - 12, 3):  # the sweep comes back over the same desk: a loop every third keyframe
        graph.add_edge(i, i + 12, _loop_measurement(truth, i, i + 12, rng), kind="loop")
    graph.optimize(max_iterations=100)
    poses = graph.nodes
    estimated = np.stack([poses[k] for k in range(KEYFRAMES)])
    centres = np.stack([t[:3, 3] for t in truth])
    extent = float(np.linalg.norm(centres - centres.mean(0), axis=1).mean())
    ate = ate_rmse(estimated, np.stack(truth))
    scales = np.array([float(sim3_decompose(torch.from_numpy(poses[k]))[0]) for k in range(KEYFRAMES)])
    unit_error = np.log(scales * SHRINK ** np.arange(KEYFRAMES))  # a keyframe's unit should undo the shrinking
    return ate / extent, float(np.ptp(unit_error))


def test_loops_take_out_the_scale_drift_that_the_default_graph_keeps() -> None:
    default_ate, default_scale = _solve(pose_graph(SlamConfig(), monocular=True))
    monocular_ate, monocular_scale = _solve(pose_graph(SlamConfig(loop=DRIFT), monocular=True))
    assert monocular_ate < 0.7 * default_ate
    assert monocular_scale < 0.5 * default_scale


def test_the_settings_reach_the_graph_and_metric_graphs_keep_theirs() -> None:
    config = SlamConfig(loop={"monocular_scale_sigma": 0.07, "monocular_loop_translation_sigma": 0.06,
                              "monocular_loop_scale_sigma": 0.08, "monocular_robust_k": 4.0})
    graph = pose_graph(config, monocular=True)
    assert graph.sigmas["sequential"].log_scale == 0.07 and graph.sigmas["sequential"].rotation == 0.01
    assert (graph.sigmas["loop"].translation, graph.sigmas["loop"].log_scale) == (0.06, 0.08)
    assert graph.robust_k == 4.0
    metric = pose_graph(config, metric=True, monocular=True)  # scale known: nothing monocular applies
    assert metric.sigmas["sequential"].log_scale < 1e-3 and metric.robust_k == config.loop.robust_k
    assert metric.sigmas["loop"].translation == 0.02
