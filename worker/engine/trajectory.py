"""The engine's trajectory: keyframe poses (what the pose graph optimises) and every frame tied to a keyframe.

Each frame stores its pose relative to its reference keyframe (the latest keyframe at or before it) as tracking
measured it; its world pose is the keyframe's current pose times that relative pose. A pose-graph update therefore
moves every frame with its keyframe (paper 4.2) and bumps the revision, so clients know the past was rewritten.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from worker.geometry import sim3_inverse


def _inv(T: np.ndarray) -> np.ndarray:
    return sim3_inverse(torch.from_numpy(np.asarray(T, np.float64))).numpy()


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    keyframe: int  # reference keyframe id
    relative: np.ndarray  # T_kf^-1 T_frame, from tracking
    is_keyframe: bool
    submap_id: int


class Trajectory:
    """Keyframe poses by keyframe id (ids are frame indices) and per-frame records, with a revision counter."""

    def __init__(self) -> None:
        self.frames: list[FrameRecord] = []
        self.keyframe_poses: dict[int, np.ndarray] = {}
        self.tracked_keyframe_poses: dict[int, np.ndarray] = {}
        self.revision = 0
        self._last_index: int | None = None

    def add_keyframe(self, kf_id: int, tracked_pose: np.ndarray, reference: int | None = None) -> np.ndarray:
        """Add keyframe `kf_id` from its tracked pose; returns its world pose. With a `reference` keyframe, the
        new keyframe follows that keyframe's corrections (its tracked relative pose is kept), so a keyframe after a
        loop closure starts from the corrected trajectory, not from the drifted odometry."""
        tracked = np.asarray(tracked_pose, np.float64).copy()
        pose = tracked
        if reference is not None:
            pose = self.keyframe_poses[reference] @ _inv(self.tracked_keyframe_poses[reference]) @ tracked
        self.tracked_keyframe_poses[int(kf_id)] = tracked
        self.keyframe_poses[int(kf_id)] = pose
        return pose

    def add_frame(self, index: int, timestamp: float, keyframe: int, tracked_pose: np.ndarray, is_keyframe: bool,
                  submap_id: int) -> np.ndarray:
        """Record a frame from its tracked pose, tied to `keyframe`; returns its world pose now."""
        if self._last_index is not None and index <= self._last_index:
            raise ValueError(f"frame index {index} is not after the previous frame {self._last_index}")
        rel = _inv(self.tracked_keyframe_poses[keyframe]) @ np.asarray(tracked_pose, np.float64)
        self.frames.append(FrameRecord(int(index), float(timestamp), int(keyframe), rel, bool(is_keyframe),
                                       int(submap_id)))
        self._last_index = int(index)
        return self.pose_of(self.frames[-1])

    def pose_of(self, record: FrameRecord) -> np.ndarray:
        return self.keyframe_poses[record.keyframe] @ record.relative

    def pose_at(self, index: int) -> np.ndarray:
        """The current world pose of frame `index` (recent frames are found first)."""
        for record in reversed(self.frames):
            if record.index == index:
                return self.pose_of(record)
        raise ValueError(f"frame {index} is not in the trajectory")

    def revise_frames(self, poses: dict[int, np.ndarray]) -> int:
        """Replace the tracked poses of past non-keyframes (a pose source re-estimated them, e.g. the frames
        before a monocular initialisation); returns the new revision."""
        for record in self.frames:
            if record.index in poses and not record.is_keyframe:
                record.relative = _inv(self.tracked_keyframe_poses[record.keyframe]) @ np.asarray(
                    poses[record.index], np.float64)
        self.revision += 1
        return self.revision

    def update_keyframes(self, poses: dict[int, np.ndarray]) -> int:
        """Replace keyframe poses (after PGO); returns the new revision."""
        for kf, pose in poses.items():
            if kf not in self.keyframe_poses:
                raise ValueError(f"unknown keyframe {kf}")
            self.keyframe_poses[int(kf)] = np.asarray(pose, np.float64).copy()
        self.revision += 1
        return self.revision

    def listing(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]:
        """[(index, timestamp, pose c2w 4x4)] for "all" frames or only "keyframes"."""
        if which not in ("all", "keyframes"):
            raise ValueError(f"trajectory kind must be 'all' or 'keyframes', got {which!r}")
        return [(r.index, r.timestamp, self.pose_of(r)) for r in self.frames if which == "all" or r.is_keyframe]

    def state_dict(self) -> dict:
        kf = sorted(self.keyframe_poses)
        return {
            "revision": self.revision,
            "keyframe_ids": np.asarray(kf, np.int64),
            "keyframe_poses": np.stack([self.keyframe_poses[k] for k in kf]) if kf else np.zeros((0, 4, 4)),
            "tracked_keyframe_poses": (np.stack([self.tracked_keyframe_poses[k] for k in kf]) if kf
                                       else np.zeros((0, 4, 4))),
            "index": np.asarray([r.index for r in self.frames], np.int64),
            "timestamp": np.asarray([r.timestamp for r in self.frames], np.float64),
            "keyframe": np.asarray([r.keyframe for r in self.frames], np.int64),
            "relative": np.stack([r.relative for r in self.frames]) if self.frames else np.zeros((0, 4, 4)),
            "is_keyframe": np.asarray([r.is_keyframe for r in self.frames], bool),
            "submap_id": np.asarray([r.submap_id for r in self.frames], np.int64),
        }

    def load_state_dict(self, d: dict) -> None:
        self.revision = int(d["revision"])
        self.keyframe_poses = {int(k): np.asarray(p, np.float64) for k, p in zip(d["keyframe_ids"],
                                                                              d["keyframe_poses"])}
        self.tracked_keyframe_poses = {int(k): np.asarray(p, np.float64)
                                       for k, p in zip(d["keyframe_ids"], d["tracked_keyframe_poses"])}
        self.frames = [FrameRecord(int(i), float(t), int(k), np.asarray(rel, np.float64), bool(kf), int(s))
                       for i, t, k, rel, kf, s in zip(d["index"], d["timestamp"], d["keyframe"], d["relative"],
                                                      d["is_keyframe"], d["submap_id"])]
        self._last_index = self.frames[-1].index if self.frames else None
