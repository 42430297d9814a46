"""Timestamped camera trajectories: TUM text I/O and timestamp association.

TUM format: one pose per line, `timestamp tx ty tz qx qy qz qw` (camera-to-world, quaternion xyzw), '#' comments.
Poses are stored here as 4x4 float64 matrices; a Sim(3) pose keeps its rotation and translation when written (TUM
has no scale field).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from worker.data.sources.base import load_matrix_rows
from worker.geometry import quat_to_rotmat, rotmat_to_quat, sim3_decompose


@dataclass
class Trajectory:
    """Camera-to-world poses [N, 4, 4] float64 at strictly increasing timestamps [N] (seconds)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64)
        if self.poses.shape != (len(self.timestamps), 4, 4):
            raise ValueError(f"poses must be [{len(self.timestamps)}, 4, 4], got {self.poses.shape}")
        if not np.all(np.isfinite(self.poses)):
            raise ValueError("trajectory poses contain non-finite values")
        if len(self.timestamps) > 1 and np.any(np.diff(self.timestamps) <= 0):
            raise ValueError("trajectory timestamps must be strictly increasing")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """Camera centres [N, 3]."""
        return self.poses[:, :3, 3]

    def subset(self, indices: np.ndarray) -> Trajectory:
        return Trajectory(self.timestamps[indices], self.poses[indices])

    @classmethod
    def from_frame_results(cls, results) -> Trajectory:
        """Trajectory of a list of FrameResult (or dicts with timestamp and pose), sorted by timestamp."""
        stamps, poses = [], []
        for r in results:
            get = r.get if isinstance(r, dict) else lambda key, r=r: getattr(r, key)
            stamps.append(float(get("timestamp")))
            poses.append(np.asarray(get("pose"), dtype=np.float64))
        order = np.argsort(stamps, kind="stable")
        return cls(np.asarray(stamps)[order], np.asarray(poses).reshape(-1, 4, 4)[order])


def poses_from_tum_rows(rows: np.ndarray) -> np.ndarray:
    """[N, 4, 4] poses from TUM rows [N, 7 or 8] (`[t] tx ty tz qx qy qz qw`; the last 7 columns are used)."""
    rows = np.asarray(rows, dtype=np.float64)
    t, q_xyzw = rows[:, -7:-4], rows[:, -4:]
    norms = np.linalg.norm(q_xyzw, axis=1)
    if np.any(norms < 1e-6):
        raise ValueError("TUM trajectory has a zero quaternion")
    q_wxyz = torch.from_numpy(q_xyzw[:, [3, 0, 1, 2]])
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = quat_to_rotmat(q_wxyz).numpy()
    poses[:, :3, 3] = t
    return poses


def tum_rows_from_poses(poses: np.ndarray) -> np.ndarray:
    """TUM columns [N, 7] `tx ty tz qx qy qz qw` of poses [N, 4, 4] (scale removed from Sim(3) rotations)."""
    _, R, t = sim3_decompose(torch.from_numpy(np.asarray(poses, dtype=np.float64)).reshape(-1, 4, 4))
    q = rotmat_to_quat(R).numpy()
    return np.concatenate([t.numpy(), q[:, [1, 2, 3, 0]]], axis=1)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file. Raises ValueError with the line number on malformed lines."""
    path = Path(path)
    data = load_matrix_rows(path, 8)  # t tx ty tz qx qy qz qw
    if not len(data):
        raise ValueError(f"{path}: no poses")
    return Trajectory(data[:, 0], poses_from_tum_rows(data))


def format_tum(trajectory: Trajectory) -> str:
    """TUM text of a trajectory (full float precision)."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, row in zip(trajectory.timestamps, tum_rows_from_poses(trajectory.poses)):
        lines.append(" ".join([f"{stamp:.9f}"] + [repr(float(v)) for v in row]))
    return "\n".join(lines) + "\n"


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write a trajectory as a TUM file."""
    Path(path).write_text(format_tum(trajectory))


def associate(
    first: np.ndarray, second: np.ndarray, max_difference: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) matching timestamps first[i] ~ second[j], each index used at most once.

    Greedy on the smallest differences first (as TUM's associate.py and evo do); pairs further apart than
    max_difference are dropped. Returns index arrays sorted by first.
    """
    first = np.asarray(first, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    if len(first) == 0 or len(second) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    # Nearest candidates: for each first stamp, the two neighbours in the sorted second list.
    order = np.argsort(second)
    sorted_second = second[order]
    pos = np.searchsorted(sorted_second, first)
    candidates = []
    for offset in (-1, 0):
        j = np.clip(pos + offset, 0, len(second) - 1)
        diff = np.abs(sorted_second[j] - first)
        candidates.append(np.stack([diff, np.arange(len(first)), order[j]], axis=1))
    pairs = np.concatenate(candidates)
    pairs = pairs[pairs[:, 0] <= max_difference]
    pairs = pairs[np.lexsort((pairs[:, 2], pairs[:, 1], pairs[:, 0]))]
    used_first, used_second, matches = set(), set(), []
    for _, i, j in pairs:
        i, j = int(i), int(j)
        if i in used_first or j in used_second:
            continue
        used_first.add(i)
        used_second.add(j)
        matches.append((i, j))
    matches.sort()
    if not matches:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    idx = np.asarray(matches, dtype=np.int64)
    return idx[:, 0], idx[:, 1]


def associate_trajectories(
    estimate: Trajectory, reference: Trajectory, max_difference: float = 0.01
) -> tuple[Trajectory, Trajectory]:
    """The matched sub-trajectories (estimate, reference) with equal length. Raises if nothing matches."""
    i, j = associate(estimate.timestamps, reference.timestamps, max_difference)
    if len(i) == 0:
        raise ValueError(f"no timestamps of the estimate match the reference within {max_difference} s")
    return estimate.subset(i), reference.subset(j)
