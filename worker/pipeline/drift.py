"""Synthetic odometry drift for given poses: how loop closure is tested on datasets with exact poses.

The model is that of a dead-reckoning odometry: every frame-to-frame motion is measured with an error, and the
errors compound along the chain. With the true poses T_k (camera-to-world) and the true motion
D_k = T_{k-1}^-1 T_k, the drifted poses are

    T'_0 = T_0,    T'_k = T'_{k-1} D_k exp(e_k),    e_k = (omega_k, tau_k) in the camera frame,
    omega_k = b_rot * a_rot + n_rot,    tau_k = b_trans * a_trans + n_trans,

with per-frame bias magnitudes b_rot (degrees) and b_trans (metres) along fixed unit axes a_rot, a_trans (drawn
once from the seed: a gyro-like heading bias and a velocity bias) and zero-mean Gaussian noise n whose norm has an
RMS of the given per-frame noise. A rotation error turns every later motion, so the position error grows faster
than linearly, as it does for real visual odometry. Deterministic for a seed.

A jump (ARKit/ARCore relocalising: `jump_frame` >= 0) moves the drifted poses of that frame and every later one by a
fixed world-frame offset of `jump_translation` metres and `jump_rotation_deg` degrees about seeded axes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from worker.geometry import relative_transform, se3_exp


@dataclass(frozen=True)
class PoseDrift:
    """Per-frame odometry error: bias (degrees, metres) and noise RMS (degrees, metres), compounded frame by frame.

    `PoseDrift(deg, m)` is a pure bias of `deg` degrees and `m` metres per frame."""

    rotation_bias_deg: float = 0.0
    translation_bias: float = 0.0
    rotation_noise_deg: float = 0.0
    translation_noise: float = 0.0
    seed: int = 0
    jump_frame: int = -1
    jump_translation: float = 0.0
    jump_rotation_deg: float = 0.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if name not in ("seed", "jump_frame") and (not math.isfinite(value) or value < 0):
                raise ValueError(f"drift {name} must be a finite value >= 0, got {value}")

    def to_dict(self) -> dict:
        return asdict(self)

    def injector(self) -> DriftInjector:
        """A fresh stateful injector: feed it the true poses in order."""
        return DriftInjector(self)

    def apply_to_trajectory(self, poses: np.ndarray) -> np.ndarray:
        """Drifted copies [N,4,4] of true c2w poses [N,4,4] (frame order)."""
        injector = self.injector()
        return np.stack([injector.apply(p) for p in np.asarray(poses, np.float64)])


class DriftInjector:
    """Applies a `PoseDrift` to a stream of true poses (see the module docstring)."""

    def __init__(self, drift: PoseDrift) -> None:
        self.drift = drift
        rng = np.random.default_rng(drift.seed)
        self._rng = rng
        self._rot_axis = _unit(rng.standard_normal(3))
        self._trans_axis = _unit(rng.standard_normal(3))
        self._previous_true: np.ndarray | None = None
        self._previous_drifted: np.ndarray | None = None
        self._frames = 0
        jump_axes = np.random.default_rng(drift.seed + 1).standard_normal((2, 3))
        self._jump = se3_exp(torch.from_numpy(np.concatenate([
            drift.jump_translation * _unit(jump_axes[0]),
            math.radians(drift.jump_rotation_deg) * _unit(jump_axes[1])]))).numpy()

    def apply(self, pose: np.ndarray) -> np.ndarray:
        """The drifted version of the next true c2w pose."""
        pose = np.asarray(pose, np.float64)
        if self._previous_true is None:
            drifted = pose.copy()
        else:
            motion = relative_transform(torch.from_numpy(self._previous_true), torch.from_numpy(pose)).numpy()
            drifted = self._previous_drifted @ motion @ self._error()
        self._previous_true, self._previous_drifted = pose.copy(), drifted
        jumped = 0 <= self.drift.jump_frame <= self._frames
        self._frames += 1
        return self._jump @ drifted if jumped else drifted.copy()

    def _error(self) -> np.ndarray:
        d = self.drift
        noise = self._rng.standard_normal(6) / math.sqrt(3.0)  # each 3-vector has unit RMS norm
        omega = math.radians(d.rotation_bias_deg) * self._rot_axis + math.radians(d.rotation_noise_deg) * noise[3:]
        tau = d.translation_bias * self._trans_axis + d.translation_noise * noise[:3]
        return se3_exp(torch.from_numpy(np.concatenate([tau, omega]))).numpy()


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)
