"""Loop detection: one global descriptor per keyframe, a temporal exclusion window and the top-k candidates.

Candidates are only proposals: each must then pass a relocalizer's verification (worker.loop.relocalize).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .descriptors import GlobalDescriptor


@dataclass(frozen=True)
class LoopCandidate:
    """Keyframe `match` (old) proposed as a revisit of keyframe `query` (current), with the descriptor score."""

    query: int
    match: int
    score: float


class LoopDetector:
    """Keyframe database for one descriptor.

    exclusion_window: keyframes whose index is within this many frames of the query are never candidates (they
    overlap by recency, not by revisiting). top_k: at most this many candidates per query, best first, each
    scoring at least `min_score`.
    """

    def __init__(self, descriptor: GlobalDescriptor, exclusion_window: int = 30, top_k: int = 3,
                 min_score: float = 0.1) -> None:
        if exclusion_window < 0 or top_k < 1:
            raise ValueError("exclusion_window must be >= 0 and top_k >= 1")
        self.descriptor = descriptor
        self.exclusion_window = exclusion_window
        self.top_k = top_k
        self.min_score = min_score
        self.indices: list[int] = []
        self.entries: list[Any] = []

    def __len__(self) -> int:
        return len(self.indices)

    def add(self, index: int, image: torch.Tensor | None = None, descriptor: Any = None) -> Any:
        """Store keyframe `index` (pass its image, or a descriptor computed before). Returns the descriptor."""
        if self.indices and index <= self.indices[-1]:
            raise ValueError(f"keyframes must be added in increasing order ({index} after {self.indices[-1]})")
        if descriptor is None:
            if image is None:
                raise ValueError("add needs an image or a descriptor")
            descriptor = self.descriptor.describe(image)
        self.indices.append(int(index))
        self.entries.append(descriptor)
        return descriptor

    def descriptor_of(self, index: int) -> Any:
        return self.entries[self.indices.index(index)]

    def query(self, index: int, image: torch.Tensor | None = None, descriptor: Any = None) -> list[LoopCandidate]:
        """Top-k old keyframes resembling keyframe `index` (outside the exclusion window)."""
        if descriptor is None:
            if image is None:
                raise ValueError("query needs an image or a descriptor")
            descriptor = self.descriptor.describe(image)
        eligible = [n for n, k in enumerate(self.indices) if k < index - self.exclusion_window]
        if not eligible:
            return []
        scores = self.descriptor.similarities(descriptor, [self.entries[n] for n in eligible])
        order = np.argsort(-scores, kind="stable")[: self.top_k]
        return [LoopCandidate(int(index), self.indices[eligible[o]], float(scores[o]))
                for o in order if scores[o] >= self.min_score]

    def detect(self, index: int, image: torch.Tensor) -> list[LoopCandidate]:
        """Query with a new keyframe, then add it to the database."""
        descriptor = self.descriptor.describe(image)
        candidates = self.query(index, descriptor=descriptor)
        self.add(index, descriptor=descriptor)
        return candidates
