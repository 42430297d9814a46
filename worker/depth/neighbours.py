"""Which frames to match a keyframe against: enough parallax, overlapping views, baselines in varied directions."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from .config import MultiViewDepthConfig
from .sweep import pose_problem

log = logging.getLogger(__name__)


def select_neighbours(ref_pose: np.ndarray, candidate_poses: Sequence[np.ndarray] | np.ndarray,
                      config: MultiViewDepthConfig | None = None, scene_depth: float | None = None) -> list[int]:
    """Indices of up to `config.num_views` candidates (camera-to-world 4x4 poses) to match `ref_pose` against.

    A candidate qualifies when baseline / scene_depth lies in [min_parallax, max_parallax] and its optical axis is
    within max_view_angle_deg of the keyframe's. Among those, the one nearest target_parallax (log scale) with the
    smallest view angle comes first; later picks are penalised for baselines pointing the same way as earlier ones
    (views on different sides see around different occluders). `scene_depth` is the keyframe's typical depth in
    pose units; None assumes the median candidate baseline is at target_parallax. Unusable poses (NaN...) are skipped.
    """
    config = config or MultiViewDepthConfig()
    ref_pose = np.asarray(ref_pose, dtype=np.float64)
    if (problem := pose_problem(ref_pose)) is not None:
        log.warning("select_neighbours: keyframe pose unusable (%s); no neighbours", problem)
        return []
    usable = [i for i, pose in enumerate(candidate_poses) if pose_problem(np.asarray(pose)) is None]
    if len(usable) < len(candidate_poses):
        log.warning("select_neighbours: skipped %d candidates with unusable poses", len(candidate_poses) - len(usable))
    if not usable:
        return []
    poses = np.stack([np.asarray(candidate_poses[i], dtype=np.float64) for i in usable])
    offsets = poses[:, :3, 3] - ref_pose[:3, 3]
    baselines = np.linalg.norm(offsets, axis=1)
    if scene_depth is None:
        median = float(np.median(baselines))
        scene_depth = median / config.target_parallax if median > 0 else 1.0
    parallax = baselines / scene_depth

    def axis(pose: np.ndarray) -> np.ndarray:
        z = pose[..., :3, 2]
        return z / np.linalg.norm(z, axis=-1, keepdims=True)

    angles = np.degrees(np.arccos(np.clip(axis(poses) @ axis(ref_pose), -1.0, 1.0)))
    eligible = (parallax >= config.min_parallax) & (parallax <= config.max_parallax) & \
               (angles <= config.max_view_angle_deg)
    score = np.abs(np.log(np.maximum(parallax, 1e-12) / config.target_parallax)) + angles / config.max_view_angle_deg
    directions = offsets / np.maximum(baselines, 1e-12)[:, None]
    chosen: list[int] = []
    remaining = list(np.flatnonzero(eligible))
    while remaining and len(chosen) < config.num_views:
        penalty = [0.5 * max([0.0] + [float(directions[i] @ directions[j]) for j in chosen]) for i in remaining]
        pick = remaining[int(np.argmin(score[remaining] + np.array(penalty)))]
        chosen.append(pick)
        remaining.remove(pick)
    return [usable[i] for i in chosen]


def looked_at_depth(ref_pose: np.ndarray, candidate_poses: Sequence[np.ndarray] | np.ndarray,
                    min_angle_deg: float = 5.0) -> float | None:
    """The typical depth of the scene from the poses alone: the median distance, along the keyframe's optical axis,
    of the points where the candidates' optical axes pass closest to it (cameras around an object or a room corner
    look at a common place), counting candidates whose axes turn by at least `min_angle_deg` from the keyframe's
    and meet it in front of both cameras; None when fewer than two do (parallel axes: a sideways pan)."""
    ref_pose = np.asarray(ref_pose, dtype=np.float64)
    origin, axis = ref_pose[:3, 3], ref_pose[:3, 2] / np.linalg.norm(ref_pose[:3, 2])
    depths = []
    for pose in candidate_poses:
        pose = np.asarray(pose, dtype=np.float64)
        if pose_problem(pose) is not None:
            continue
        other, direction = pose[:3, 3], pose[:3, 2] / np.linalg.norm(pose[:3, 2])
        cos = float(axis @ direction)
        if np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) < min_angle_deg:
            continue
        # closest points origin + s axis and other + t direction of the two lines
        w = origin - other
        denom = 1.0 - cos * cos
        s = (cos * (direction @ w) - (axis @ w)) / denom
        t = ((direction @ w) - cos * (axis @ w)) / denom
        if s > 0 and t > 0:
            depths.append(s)
    return float(np.median(depths)) if len(depths) >= 2 else None
