"""An inverted index over a visual vocabulary: for each word, the database entries whose bag holds it.

A query touches only the entries that share a word with it, word by word, and scores them with the L1 score of
the bags (worker.loop.vocabulary): for L1-normalised non-negative bags q and d, 1 - |q - d|_1 / 2 equals
sum_w min(q_w, d_w) over the words both hold. The cost is the length of the query words' posting lists, a small
fraction of the database per word with no Python work per entry, instead of a dense comparison with every bag.
"""

from __future__ import annotations

import numpy as np

from .vocabulary import SparseBag

_INITIAL_CAPACITY = 8


class InvertedIndex:
    """Posting lists (entry row, word weight) per word for bags added in row order 0, 1, 2, ..."""

    def __init__(self, vocabulary_size: int) -> None:
        if vocabulary_size < 1:
            raise ValueError(f"vocabulary size must be >= 1, got {vocabulary_size}")
        self.vocabulary_size = vocabulary_size
        self._rows = [np.empty(0, np.int32) for _ in range(vocabulary_size)]
        self._weights = [np.empty(0, np.float32) for _ in range(vocabulary_size)]
        self._counts = np.zeros(vocabulary_size, np.int64)
        self._entries = 0

    def __len__(self) -> int:
        return self._entries

    def add(self, bag: SparseBag) -> int:
        """Append one entry's bag; returns its row."""
        if len(bag.words) and (bag.words.min() < 0 or bag.words.max() >= self.vocabulary_size):
            raise ValueError(f"word ids must lie in [0, {self.vocabulary_size})")
        row = self._entries
        for word, weight in zip(bag.words.tolist(), bag.weights.tolist()):
            n = self._counts[word]
            if n == len(self._rows[word]):
                capacity = max(_INITIAL_CAPACITY, 2 * n)
                self._rows[word] = np.resize(self._rows[word], capacity)
                self._weights[word] = np.resize(self._weights[word], capacity)
            self._rows[word][n] = row
            self._weights[word][n] = weight
            self._counts[word] = n + 1
        self._entries += 1
        return row

    def scores(self, bag: SparseBag, below: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """L1 scores of the query `bag` against rows [0, below) (all rows by default): (scores [below] with 0 for
        the entries sharing no word, shared word counts [below])."""
        below = self._entries if below is None else min(int(below), self._entries)
        if below <= 0 or not len(bag.words):
            return np.zeros(max(below, 0)), np.zeros(max(below, 0), np.int64)
        counts = self._counts[bag.words]
        rows = np.concatenate([self._rows[w][:n] for w, n in zip(bag.words.tolist(), counts.tolist())])
        weights = np.concatenate([self._weights[w][:n] for w, n in zip(bag.words.tolist(), counts.tolist())])
        shared = np.minimum(weights, np.repeat(bag.weights, counts))
        keep = rows < below
        rows = rows[keep]
        return (np.bincount(rows, shared[keep], minlength=below).astype(np.float64),
                np.bincount(rows, minlength=below))
