"""Every keyframe visual odometry made, with what it observed, for the final bundle adjustment
(`worker.tracking.global_adjustment`): the local map forgets keyframes and points as its window slides, this keeps
them (bounded by `final_adjustment_keyframes`, the oldest go first).

The archive lives only in memory: a session resumed from a snapshot archives the keyframes made after the resume.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np


@dataclass
class ArchivedKeyframe:
    """One keyframe: frame index, pose (camera-to-world, the map's coordinates), its point observations (pixels
    [n, 2], the points' ids [n], pyramid octaves [n]) and its ORB features that lie on those points (keypoints
    [m, 2], descriptors [m, 32], the points' ids [m]), by which a later keyframe recognises the same points;
    `handed_out`: the pose odometry gave its frame (later windowed adjustments moved `pose` on from there)."""

    index: int
    pose: np.ndarray
    uv: np.ndarray
    point_ids: np.ndarray
    octaves: np.ndarray
    orb_keypoints: np.ndarray
    orb_descriptors: np.ndarray
    orb_point_ids: np.ndarray
    handed_out: np.ndarray | None = None


class KeyframeArchive:
    """Archived keyframes by frame index (a keyframe archived again replaces its entry: its newest pose) and the
    position of each point when it was last archived."""

    def __init__(self, max_keyframes: int) -> None:
        self.max_keyframes = max_keyframes
        self.keyframes: OrderedDict[int, ArchivedKeyframe] = OrderedDict()
        self.positions: dict[int, np.ndarray] = {}
        self.handed_out: dict[int, np.ndarray] = {}  # keyframes not archived yet: the pose their frame was given
        self.map_token: int | None = None
        self.mixed_maps = False  # keyframes of two maps (a restart after a loss): no common coordinates

    def __len__(self) -> int:
        return len(self.keyframes)

    def note_handed_out(self, index: int, pose: np.ndarray) -> None:
        """The pose odometry gave keyframe `index`'s frame (kept until the keyframe is archived)."""
        if self.max_keyframes:
            self.handed_out[index] = np.array(pose, np.float64)

    def record(self, keyframe: ArchivedKeyframe, positions: dict[int, np.ndarray], map_token: int) -> None:
        """Archive `keyframe` and its points' positions (`positions`: point id -> [3]) from the map `map_token`
        names (one token a map: keyframes of another map mark the archive mixed)."""
        if self.map_token is not None and map_token != self.map_token:
            self.mixed_maps = True
        self.map_token = map_token
        earlier = self.keyframes.pop(keyframe.index, None)
        given = self.handed_out.pop(keyframe.index, None)
        keyframe.handed_out = earlier.handed_out if earlier is not None else given
        self.keyframes[keyframe.index] = keyframe
        self.positions.update(positions)
        if len(self.keyframes) > self.max_keyframes:
            while len(self.keyframes) > self.max_keyframes:
                self.keyframes.popitem(last=False)
            if len(self.positions) > 2 * sum(len(k.point_ids) for k in self.keyframes.values()):
                seen = set(np.concatenate([k.point_ids for k in self.keyframes.values()]).tolist())
                self.positions = {i: x for i, x in self.positions.items() if i in seen}

    def ordered(self) -> list[ArchivedKeyframe]:
        """The archived keyframes by frame index."""
        return [self.keyframes[k] for k in sorted(self.keyframes)]
