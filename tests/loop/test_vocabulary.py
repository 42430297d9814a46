"""The ORB visual vocabulary: k-majority clustering, tree quantization, tf-idf bags (dense and sparse)."""

from __future__ import annotations

import numpy as np
import pytest

from worker.loop.descriptors import OrbDescriptor, default_vocabulary
from worker.loop.vocabulary import Vocabulary, hamming, k_majority, train_vocabulary


def _noisy_copies(centres: np.ndarray, per_centre: int, flips: int, rng: np.random.Generator) -> np.ndarray:
    """Copies of each centre with `flips` random bits flipped, shuffled."""
    bits = np.repeat(np.unpackbits(centres, axis=1), per_centre, axis=0)
    for row in bits:
        row[rng.choice(256, flips, replace=False)] ^= 1
    return np.packbits(bits, axis=1)[rng.permutation(len(bits))]


def test_hamming_counts_differing_bits():
    a = np.zeros((1, 32), np.uint8)
    b = a.copy()
    b[0, 0], b[0, 31] = 0b1011, 0xFF
    assert hamming(a, b).tolist() == [11]
    assert hamming(b, b).tolist() == [0]


def test_k_majority_recovers_the_centres_of_noisy_copies():
    rng = np.random.default_rng(0)
    centres = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    found = k_majority(_noisy_copies(centres, 60, 20, rng), 4, rng)
    assert sorted(map(bytes, found)) == sorted(map(bytes, centres))


def _hierarchical_centres(rng: np.random.Generator, branching: int, flips: int) -> np.ndarray:
    """branching**2 leaf centres: `branching` random parents, each with children `flips` bits away."""
    parents = rng.integers(0, 256, (branching, 32), dtype=np.uint8)
    return _noisy_copies(parents, branching, flips, rng)


def test_words_group_near_descriptors_and_bags_score_by_shared_words():
    rng = np.random.default_rng(1)
    leaves = _hierarchical_centres(rng, 3, 40)
    images = [_noisy_copies(leaves[k:k + 1], 40, 6, rng) for k in range(9)]  # one place (cluster) per image
    vocabulary = train_vocabulary(images, branching=3, levels=2)
    assert vocabulary.size == 9
    words = [set(vocabulary.quantize(d).tolist()) for d in images]
    assert all(len(w) == 1 for w in words)  # every copy of a place gets the same word
    assert len(set().union(*words)) == 9  # and different places get different words
    bags = np.stack([vocabulary.bag_of_words(d) for d in images])
    np.testing.assert_allclose(bags.sum(axis=1), 1.0, rtol=1e-6)
    mixed = vocabulary.bag_of_words(np.concatenate([images[0], images[1]]))
    scores = Vocabulary.score(mixed, bags)
    assert scores[0] == pytest.approx(0.5, abs=1e-6) and scores[1] == pytest.approx(0.5, abs=1e-6)
    assert np.all(scores[2:] < 1e-6)


def test_save_load_round_trip_and_bad_files(tmp_path):
    rng = np.random.default_rng(2)
    vocabulary = train_vocabulary([rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(3)], 4, 2)
    vocabulary.save(tmp_path / "v.npz")
    loaded = Vocabulary.load(tmp_path / "v.npz")
    probe = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    assert np.array_equal(loaded.quantize(probe), vocabulary.quantize(probe))
    np.savez(tmp_path / "bad.npz", branching=np.array(4), idf=np.zeros(16, np.float32),
             level0=np.zeros((3, 32), np.uint8), level1=np.zeros((16, 32), np.uint8))
    with pytest.raises(ValueError, match="level 0"):
        Vocabulary.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="uint8 binary descriptors"):
        vocabulary.quantize(np.zeros((3, 16), np.uint8))


def test_shipped_vocabulary_is_usable():
    vocabulary = default_vocabulary()
    assert vocabulary.size >= 1000
    assert np.all(np.isfinite(vocabulary.idf)) and np.all(vocabulary.idf >= 0)


def test_sparse_bag_is_the_dense_bag(icl_frames):
    vocabulary = default_vocabulary()
    orb = OrbDescriptor(n_features=500)
    for frame in icl_frames[:5]:
        descriptors = orb.describe(frame.image).descriptors
        sparse = vocabulary.sparse_bag(descriptors)
        assert np.all(np.diff(sparse.words) > 0) and np.all(sparse.weights > 0)
        np.testing.assert_allclose(sparse.dense(vocabulary.size), vocabulary.bag_of_words(descriptors), atol=1e-6)
    empty = vocabulary.sparse_bag(np.zeros((0, 32), np.uint8))
    assert len(empty.words) == 0 and empty.dense(vocabulary.size).sum() == 0
