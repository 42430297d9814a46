"""The local map: a window of keyframes and the 3D points they observe (bounded: points nobody in the window sees
are dropped when the window slides)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .bundle_adjustment import Observations
from .features import Features

_GENERATIONS = itertools.count()  # tells maps apart in memory (a map restarted after a loss numbers points anew)


@dataclass
class Keyframe:
    """A keyframe: its frame index, camera-to-world pose, features and, per keypoint, the point row it observes
    (-1: none) and the optical-flow track it belongs to (-1: none); `orb`: the ORB features of its image, for
    relocalisation (empty when the image was not kept)."""

    index: int
    pose: np.ndarray
    features: Features
    point_ids: np.ndarray
    track_ids: np.ndarray | None = None
    orb: Features | None = None

    def __post_init__(self) -> None:
        if self.track_ids is None:
            self.track_ids = np.full(len(self.point_ids), -1, np.int64)
        if self.orb is None:
            self.orb = Features.empty()

    def to_state(self) -> dict:
        return {"index": self.index, "pose": self.pose, "features": self.features.to_state(),
                "point_ids": self.point_ids, "track_ids": self.track_ids, "orb": self.orb.to_state()}

    @classmethod
    def from_state(cls, state: dict) -> Keyframe:
        return cls(int(state["index"]), np.asarray(state["pose"], np.float64).reshape(4, 4),
                   Features.from_state(state["features"]), np.asarray(state["point_ids"], np.int64).reshape(-1),
                   np.asarray(state["track_ids"], np.int64).reshape(-1), Features.from_state(state["orb"]))


class LocalMap:
    """Points (positions [P, 3], descriptors [P, 32], times projected into the image and times matched, ids that
    stay when rows are renumbered) and the keyframe window that observes them."""

    def __init__(self) -> None:
        self.keyframes: list[Keyframe] = []
        self.positions = np.zeros((0, 3))
        self.descriptors = np.zeros((0, 32), np.uint8)
        self.visible = np.zeros(0, np.int64)
        self.found = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.next_id = 0
        self.generation = next(_GENERATIONS)

    def __len__(self) -> int:
        return len(self.positions)

    def add_points(self, positions: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
        """Append points; returns their rows."""
        start = len(self.positions)
        self.positions = np.concatenate([self.positions, positions.reshape(-1, 3)])
        self.descriptors = np.concatenate([self.descriptors, descriptors.reshape(-1, 32)])
        self.visible = np.concatenate([self.visible, np.ones(len(positions), np.int64)])
        self.found = np.concatenate([self.found, np.ones(len(positions), np.int64)])
        added = len(self.positions) - start
        self.ids = np.concatenate([self.ids, np.arange(self.next_id, self.next_id + added)])
        self.next_id += added
        return np.arange(start, len(self.positions))

    def observations(self, sigma_of) -> Observations:
        """Every (window keyframe slot, point row, pixel, sigma) observation; sigma_of maps octaves to sigmas."""
        slots, points, uv, sigma = [], [], [], []
        for n, kf in enumerate(self.keyframes):
            kp = np.flatnonzero(kf.point_ids >= 0)
            slots.append(np.full(len(kp), n, np.int64))
            points.append(kf.point_ids[kp])
            uv.append(kf.features.keypoints[kp].astype(np.float64))
            sigma.append(sigma_of(kf.features.octaves[kp]))
        if not slots:
            return Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
        return Observations(np.concatenate(slots), np.concatenate(points), np.concatenate(uv), np.concatenate(sigma))

    def observation_counts(self) -> np.ndarray:
        counts = np.zeros(len(self.positions), np.int64)
        for kf in self.keyframes:
            np.add.at(counts, kf.point_ids[kf.point_ids >= 0], 1)
        return counts

    def forget(self, drop: np.ndarray) -> np.ndarray:
        """Remove the points whose mask `drop` [P] is set, renumbering the keyframes' references; returns the
        renumbering [P + 1] (old row -> new row, -1 for removed; index -1 maps -1 to -1)."""
        keep = ~drop
        remap = np.full(len(self.positions) + 1, -1, np.int64)
        remap[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
        for kf in self.keyframes:
            kf.point_ids = remap[kf.point_ids]  # -1 indexes the trailing -1
        self.positions, self.descriptors = self.positions[keep], self.descriptors[keep]
        self.visible, self.found, self.ids = self.visible[keep], self.found[keep], self.ids[keep]
        return remap

    def slide(self, window: int) -> list[Keyframe]:
        """Keep the last `window` keyframes; returns those that left (their point rows still valid until
        `forget_unobserved`)."""
        gone = self.keyframes[:-window] if len(self.keyframes) > window else []
        self.keyframes = self.keyframes[len(gone):]
        return gone

    def forget_unobserved(self) -> np.ndarray:
        """Drop the points no keyframe of the window observes; returns the renumbering (see `forget`)."""
        return self.forget(self.observation_counts() == 0)

    def to_state(self) -> dict:
        return {"keyframes": [kf.to_state() for kf in self.keyframes], "positions": self.positions,
                "descriptors": self.descriptors, "visible": self.visible, "found": self.found,
                "ids": self.ids, "next_id": self.next_id}

    @classmethod
    def from_state(cls, state: dict) -> LocalMap:
        m = cls()
        m.keyframes = [Keyframe.from_state(k) for k in state["keyframes"]]
        m.positions = np.asarray(state["positions"], np.float64).reshape(-1, 3)
        m.descriptors = np.asarray(state["descriptors"], np.uint8).reshape(-1, 32)
        m.visible = np.asarray(state["visible"], np.int64).reshape(-1)
        m.found = np.asarray(state["found"], np.int64).reshape(-1)
        # a snapshot from before point ids: fresh ones
        m.ids = np.asarray(state.get("ids", np.arange(len(m.positions))), np.int64).reshape(-1)
        m.next_id = int(state.get("next_id", len(m.positions)))
        return m
