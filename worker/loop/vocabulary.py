"""A visual vocabulary for binary (ORB) descriptors: a k-majority tree, tf-idf bags of words and their L1 score.

The classical loop detector verifies candidates geometrically (ratio-test matching + RANSAC, ~4 ms per pair). Doing
that against every keyframe grows linearly with the map, so the vocabulary ranks the database first (one quantization
per keyframe, one vector comparison per entry) and only a short list is verified.

The tree has `branching ** levels` leaves (words). Each node's children come from k-majority clustering (Hamming
distance, per-bit majority as the centre) of the descriptors that reached the node. Word weights are the idf of the
training images. The shipped vocabulary (`DEFAULT_PATH`) was trained on procedural synthetic rooms, never on the
evaluation data: `python -m worker.loop.vocabulary_training --out PATH` rebuilds it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

DEFAULT_PATH = Path(__file__).parent / "data" / "orb_vocabulary.npz"
DESCRIPTOR_BYTES = 32
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between uint8 descriptors a [..., 32] and b [..., 32] (broadcast)."""
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=-1, dtype=np.int32)


def _majority(descriptors: np.ndarray) -> np.ndarray:
    bits = np.unpackbits(descriptors, axis=1)
    return np.packbits(bits.mean(axis=0) >= 0.5)


def k_majority(descriptors: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 8) -> np.ndarray:
    """k centres [k, 32] of uint8 descriptors [N, 32] (k-means++ seeding, Hamming distance, bitwise majority).

    With fewer than k distinct descriptors the missing centres repeat existing ones (empty leaves)."""
    unique = np.unique(descriptors, axis=0)
    if len(unique) <= k:
        return unique[np.arange(k) % len(unique)].copy()
    centres = [descriptors[rng.integers(len(descriptors))]]
    nearest = hamming(descriptors, centres[0]).astype(np.float64)
    for _ in range(1, k):
        weights = nearest ** 2
        centres.append(descriptors[rng.choice(len(descriptors), p=weights / weights.sum())])
        nearest = np.minimum(nearest, hamming(descriptors, centres[-1]))
    centres = np.stack(centres)
    for _ in range(iterations):
        assign = hamming(descriptors[:, None, :], centres[None]).argmin(axis=1)
        updated = np.stack([_majority(descriptors[assign == j]) if np.any(assign == j) else centres[j]
                            for j in range(k)])
        if np.array_equal(updated, centres):
            break
        centres = updated
    return centres


@dataclass(frozen=True)
class SparseBag:
    """A tf-idf bag of words by its non-zero entries: sorted word ids [n] (int32) and L1-normalised weights [n]."""

    words: np.ndarray
    weights: np.ndarray

    def dense(self, size: int) -> np.ndarray:
        bag = np.zeros(size, np.float32)
        bag[self.words] = self.weights
        return bag


@dataclass
class Vocabulary:
    """`levels` arrays of node centres: level l holds branching**(l+1) centres [.., 32]; plus idf per word."""

    branching: int
    centres: list[np.ndarray]
    idf: np.ndarray

    @property
    def size(self) -> int:
        return self.branching ** len(self.centres)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id in [0, size) of each uint8 descriptor [N, 32] (greedy descent of the tree)."""
        descriptors = _check_descriptors(descriptors)
        node = np.zeros(len(descriptors), dtype=np.int64)
        children = np.arange(self.branching)
        for level in self.centres:
            candidates = level[node[:, None] * self.branching + children[None, :]]  # [N, k, 32]
            node = node * self.branching + hamming(descriptors[:, None, :], candidates).argmin(axis=1)
        return node

    def bag_of_words(self, descriptors: np.ndarray) -> np.ndarray:
        """L1-normalised tf-idf vector [size] (float32) of one image's descriptors (zeros if it has none)."""
        bag = np.zeros(self.size, dtype=np.float32)
        if len(descriptors):
            np.add.at(bag, self.quantize(descriptors), 1.0)
            bag *= self.idf
            total = bag.sum()
            if total > 0:
                bag /= total
        return bag

    def sparse_bag(self, descriptors: np.ndarray) -> SparseBag:
        """The same tf-idf bag as `bag_of_words`, as its non-zero words only."""
        descriptors = _check_descriptors(descriptors)
        if not len(descriptors):
            return SparseBag(np.zeros(0, np.int32), np.zeros(0, np.float32))
        words, counts = np.unique(self.quantize(descriptors), return_counts=True)
        weights = counts.astype(np.float32) * self.idf[words]
        keep = weights > 0
        words, weights = words[keep].astype(np.int32), weights[keep]
        total = weights.sum()
        return SparseBag(words, weights / total if total > 0 else weights)

    @staticmethod
    def score(query: np.ndarray, database: np.ndarray) -> np.ndarray:
        """L1 score in [0, 1] between a bag [V] and bags [N, V]: 1 - |q - d|_1 / 2 (1 = identical)."""
        return 1.0 - 0.5 * np.abs(database - query[None, :]).sum(axis=1)

    def save(self, path: str | Path) -> None:
        arrays = {f"level{n}": c for n, c in enumerate(self.centres)}
        np.savez_compressed(path, branching=np.array(self.branching), idf=self.idf, **arrays)

    @classmethod
    def load(cls, path: str | Path = DEFAULT_PATH) -> Vocabulary:
        """Read a vocabulary saved by `save` (plain arrays only: no pickle)."""
        with np.load(path, allow_pickle=False) as data:
            levels = sorted((k for k in data.files if k.startswith("level")), key=lambda k: int(k[5:]))
            vocabulary = cls(int(data["branching"]), [data[k] for k in levels], data["idf"].astype(np.float32))
        for n, centres in enumerate(vocabulary.centres):
            if centres.shape != (vocabulary.branching ** (n + 1), DESCRIPTOR_BYTES) or centres.dtype != np.uint8:
                raise ValueError(f"{path}: level {n} has shape {centres.shape}, dtype {centres.dtype}")
        if vocabulary.idf.shape != (vocabulary.size,):
            raise ValueError(f"{path}: idf has shape {vocabulary.idf.shape}, expected ({vocabulary.size},)")
        return vocabulary


def train_vocabulary(images: list[np.ndarray], branching: int = 10, levels: int = 3, seed: int = 0) -> Vocabulary:
    """Build a vocabulary from per-image descriptor arrays (uint8 [N_i, 32]); idf = log(#images / #images with w)."""
    if branching < 2 or levels < 1:
        raise ValueError("branching must be >= 2 and levels >= 1")
    images = [_check_descriptors(d) for d in images if len(d)]
    if not images:
        raise ValueError("no descriptors to train a vocabulary on")
    rng = np.random.default_rng(seed)
    everything = np.concatenate(images)
    members = [everything]
    centres = []
    for _ in range(levels):
        level, next_members = [], []
        for group in members:
            node_centres = k_majority(group, branching, rng) if len(group) else np.zeros(
                (branching, DESCRIPTOR_BYTES), np.uint8)
            level.append(node_centres)
            assign = hamming(group[:, None, :], node_centres[None]).argmin(axis=1) if len(group) else group[:0, 0]
            next_members.extend(group[assign == j] for j in range(branching))
        centres.append(np.concatenate(level))
        members = next_members
    vocabulary = Vocabulary(branching, centres, np.zeros(branching ** levels, np.float32))
    seen_in = np.zeros(vocabulary.size)
    for descriptors in images:
        seen_in[np.unique(vocabulary.quantize(descriptors))] += 1
    vocabulary.idf = np.log(len(images) / np.maximum(seen_in, 1.0)).astype(np.float32)
    return vocabulary


def _check_descriptors(descriptors: np.ndarray) -> np.ndarray:
    descriptors = np.asarray(descriptors)
    if descriptors.dtype != np.uint8 or descriptors.ndim != 2 or descriptors.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f"expected uint8 binary descriptors [N, {DESCRIPTOR_BYTES}], got {descriptors.dtype} "
                         f"{descriptors.shape}")
    return descriptors
