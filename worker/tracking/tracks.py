"""The points followed by optical flow from frame to frame: an id, the pixel in the latest frame and the map point
it measures (-1 while it is only a candidate waiting for enough parallax to be triangulated)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def lookup_sorted(sorted_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of `ids` in the ascending array `sorted_ids`, and the mask of those present."""
    if len(sorted_ids) == 0:
        return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
    at = np.clip(np.searchsorted(sorted_ids, ids), 0, len(sorted_ids) - 1)
    return at, sorted_ids[at] == ids


@dataclass
class Tracks:
    """Track ids [N] int64, pixels uv [N, 2] float32 in the latest frame, map point rows [N] int64 (-1: none)."""

    ids: np.ndarray
    uv: np.ndarray
    rows: np.ndarray

    @classmethod
    def empty(cls) -> Tracks:
        return cls(np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.ids)

    def subset(self, keep: np.ndarray) -> Tracks:
        """The tracks selected by a mask or index array."""
        return Tracks(self.ids[keep], self.uv[keep], self.rows[keep])

    def extend(self, ids: np.ndarray, uv: np.ndarray) -> Tracks:
        """These tracks followed by new candidate tracks (no map point)."""
        return Tracks(np.concatenate([self.ids, ids.astype(np.int64)]),
                      np.concatenate([self.uv, uv.astype(np.float32).reshape(-1, 2)]),
                      np.concatenate([self.rows, np.full(len(ids), -1, np.int64)]))

    @property
    def mapped(self) -> np.ndarray:
        """Mask of the tracks that measure a map point."""
        return self.rows >= 0

    def to_state(self) -> dict[str, np.ndarray]:
        return {"ids": self.ids, "uv": self.uv, "rows": self.rows}

    @classmethod
    def from_state(cls, state: dict) -> Tracks:
        return cls(np.asarray(state["ids"], np.int64).reshape(-1), np.asarray(state["uv"], np.float32).reshape(-1, 2),
                   np.asarray(state["rows"], np.int64).reshape(-1))
