"""Loop detection: one global descriptor per keyframe, a temporal exclusion window and the top-k candidates.

With a bag-of-words descriptor (ORB under a visual vocabulary) the database is ranked through an inverted index
(worker.loop.inverted_index) and only a bounded shortlist is scored by the descriptor's geometric verification, so
a query costs about the same with 30 or 3,000 keyframes. Candidates are only proposals: each must then pass a
relocalizer's verification (worker.loop.relocalize).
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .descriptors import GlobalDescriptor
from .inverted_index import InvertedIndex
from .vocabulary import SparseBag


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

    When the descriptor gives bags of words (`words_of`), at most `shortlist` eligible keyframes are scored per
    query: the `recent` newest ones outside the exclusion window (a slow camera overlaps them most often) and the
    ones the inverted index scores highest. Otherwise (one vector per keyframe, cheap to compare) every eligible
    keyframe is scored.
    """

    def __init__(self, descriptor: GlobalDescriptor, exclusion_window: int = 30, top_k: int = 3,
                 min_score: float = 0.1, shortlist: int = 10, recent: int = 2) -> None:
        if exclusion_window < 0 or top_k < 1:
            raise ValueError("exclusion_window must be >= 0 and top_k >= 1")
        if shortlist < 1 or not 0 <= recent <= shortlist:
            raise ValueError(f"need shortlist >= 1 and 0 <= recent <= shortlist, got {shortlist} and {recent}")
        self.descriptor = descriptor
        self.exclusion_window = exclusion_window
        self.top_k = top_k
        self.min_score = min_score
        self.shortlist = shortlist
        self.recent = recent
        vocabulary = getattr(descriptor, "vocabulary", None)
        self.index: InvertedIndex | None = None if vocabulary is None else InvertedIndex(vocabulary.size)
        self.indices: list[int] = []
        self.entries: list[Any] = []
        self._row_of: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self.indices)

    def __contains__(self, index: int) -> bool:
        return int(index) in self._row_of

    def add(self, index: int, image: torch.Tensor | None = None, descriptor: Any = None) -> Any:
        """Store keyframe `index` (pass its image, or a descriptor computed before). Returns the descriptor."""
        if self.indices and index <= self.indices[-1]:
            raise ValueError(f"keyframes must be added in increasing order ({index} after {self.indices[-1]})")
        if descriptor is None:
            if image is None:
                raise ValueError("add needs an image or a descriptor")
            descriptor = self.descriptor.describe(image)
        if self.index is not None:
            self.index.add(self._words(descriptor))
        self._row_of[int(index)] = len(self.indices)
        self.indices.append(int(index))
        self.entries.append(descriptor)
        return descriptor

    def _words(self, descriptor: Any) -> SparseBag:
        return self.descriptor.words_of(descriptor)

    def descriptor_of(self, index: int) -> Any:
        return self.entries[self._row_of[int(index)]]

    def shortlisted(self, descriptor: Any, eligible: int) -> np.ndarray:
        """Rows (ascending) among the first `eligible` entries that the descriptor will score."""
        if self.index is None or eligible <= self.shortlist:
            return np.arange(eligible)
        scores, _ = self.index.scores(self._words(descriptor), below=eligible)
        scores[eligible - self.recent:] = np.inf
        return np.sort(np.argsort(-scores, kind="stable")[: self.shortlist])

    def query(self, index: int, image: torch.Tensor | None = None, descriptor: Any = None) -> list[LoopCandidate]:
        """Top-k old keyframes resembling keyframe `index` (outside the exclusion window)."""
        if descriptor is None:
            if image is None:
                raise ValueError("query needs an image or a descriptor")
            descriptor = self.descriptor.describe(image)
        eligible = bisect_left(self.indices, index - self.exclusion_window)
        if not eligible:
            return []
        rows = self.shortlisted(descriptor, eligible)
        scores = self.descriptor.similarities(descriptor, [self.entries[r] for r in rows])
        order = np.argsort(-scores, kind="stable")[: self.top_k]
        return [LoopCandidate(int(index), self.indices[rows[o]], float(scores[o]))
                for o in order if scores[o] >= self.min_score]

    def detect(self, index: int, image: torch.Tensor) -> list[LoopCandidate]:
        """Query with a new keyframe, then add it to the database."""
        descriptor = self.descriptor.describe(image)
        candidates = self.query(index, descriptor=descriptor)
        self.add(index, descriptor=descriptor)
        return candidates

    def load(self, indices: list[int], entries: list[Any]) -> None:
        """Replace the database (a restore): keyframes in increasing order with their descriptors."""
        if len(indices) != len(entries):
            raise ValueError(f"{len(indices)} keyframe indices for {len(entries)} descriptors")
        self.indices, self.entries, self._row_of = [], [], {}
        vocabulary = getattr(self.descriptor, "vocabulary", None)
        self.index = None if vocabulary is None else InvertedIndex(vocabulary.size)
        for index, entry in zip(indices, entries):
            self.add(int(index), descriptor=entry)
