"""A pose trajectory sampled at timestamps, read at any times: slerp for rotation, linear for translation (and scale).

Vectorised over the query times: the device clock (worker.tracking.device_clock) reads a window of frames at a
whole grid of clock offsets at once. Before the first and after the last sample the end interval's constant velocity
continues, at most `max_extrapolation_s` seconds; further queries stop there.
"""

from __future__ import annotations

import numpy as np
import torch

from worker.geometry.transforms import so3_exp, so3_log


def interpolate_poses(times: np.ndarray, poses: np.ndarray, queries: np.ndarray,
                      max_extrapolation_s: float = 0.0) -> np.ndarray:
    """The c2w poses [..., 4, 4] at `queries` [...] (seconds) of the trajectory sampled at increasing `times` [n]
    with `poses` [n, 4, 4] (rigid, or similarities with a uniform scale). One sample: that pose everywhere."""
    times = np.asarray(times, np.float64)
    poses = np.asarray(poses, np.float64)
    queries = np.asarray(queries, np.float64)
    if len(times) == 0:
        raise ValueError("no pose to interpolate")
    if len(times) == 1:
        return np.broadcast_to(poses[0], queries.shape + (4, 4)).copy()
    q = np.clip(queries, times[0] - max_extrapolation_s, times[-1] + max_extrapolation_s)
    i = np.clip(np.searchsorted(times, q, side="right") - 1, 0, len(times) - 2)
    s = (q - times[i]) / np.maximum(times[i + 1] - times[i], 1e-9)
    scale = np.cbrt(np.linalg.det(poses[:, :3, :3]))
    rotation = poses[:, :3, :3] / scale[:, None, None]
    a, b = rotation[i], rotation[i + 1]
    step = so3_log(torch.from_numpy(np.swapaxes(a, -1, -2) @ b)).numpy()  # a^T b as axis-angle
    turned = a @ so3_exp(torch.from_numpy(step * s[..., None])).numpy()
    out = np.zeros(queries.shape + (4, 4))
    out[..., :3, :3] = turned * (scale[i] + s * (scale[i + 1] - scale[i]))[..., None, None]
    out[..., :3, 3] = poses[i, :3, 3] + s[..., None] * (poses[i + 1, :3, 3] - poses[i, :3, 3])
    out[..., 3, 3] = 1.0
    return out
