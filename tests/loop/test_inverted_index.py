"""The inverted index over the ORB vocabulary and the loop detector's bounded shortlist, on ICL frames."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.config import LoopConfig
from worker.loop.descriptors import OrbDescriptor, default_vocabulary
from worker.loop.detector import LoopDetector
from worker.loop.inverted_index import InvertedIndex
from worker.loop.vocabulary import SparseBag, Vocabulary
from worker.pipeline.loop_closer import DepthKeyframePoints, LoopCloser


@pytest.fixture(scope="module")
def features(icl_frames):
    orb = OrbDescriptor(n_features=500)
    return [orb.describe(frame.image) for frame in icl_frames[::2]]


def test_index_scores_equal_the_dense_l1_score(features):
    vocabulary = default_vocabulary()
    bags = [vocabulary.sparse_bag(f.descriptors) for f in features]
    index = InvertedIndex(vocabulary.size)
    assert [index.add(bag) for bag in bags] == list(range(len(bags)))
    dense = np.stack([bag.dense(vocabulary.size) for bag in bags])
    for query in (bags[0], bags[17], bags[-1]):
        scores, shared = index.scores(query)
        np.testing.assert_allclose(scores, Vocabulary.score(query.dense(vocabulary.size), dense), atol=1e-5)
        np.testing.assert_array_equal(shared, [len(np.intersect1d(query.words, b.words)) for b in bags])
        below, _ = index.scores(query, below=10)
        np.testing.assert_allclose(below, scores[:10])
    assert scores.argmax() == len(bags) - 1 and scores.max() == pytest.approx(1.0, abs=1e-5)


def test_entries_sharing_no_word_score_zero_and_bad_words_are_refused():
    index = InvertedIndex(8)
    index.add(SparseBag(np.array([0, 1], np.int32), np.array([0.5, 0.5], np.float32)))
    index.add(SparseBag(np.array([5], np.int32), np.array([1.0], np.float32)))
    scores, shared = index.scores(SparseBag(np.array([1, 2], np.int32), np.array([0.25, 0.75], np.float32)))
    np.testing.assert_allclose(scores, [0.25, 0.0])
    np.testing.assert_array_equal(shared, [1, 0])
    with pytest.raises(ValueError, match="word ids"):
        index.add(SparseBag(np.array([8], np.int32), np.array([1.0], np.float32)))


class CountingOrb(OrbDescriptor):
    """ORB that records how many entries each query verifies geometrically."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.verified: list[int] = []

    def similarities(self, query, database):
        self.verified.append(len(database))
        return super().similarities(query, database)


def test_detector_verifies_a_bounded_shortlist_of_recent_and_best_indexed_keyframes(features):
    orb = CountingOrb(n_features=500)
    detector = LoopDetector(orb, exclusion_window=3, top_k=3, min_score=0.0, shortlist=5, recent=2)
    for n, f in enumerate(features):
        detector.add(n, descriptor=f)
    query = features[-1]
    eligible = len(features) - 1 - 3
    rows = detector.shortlisted(query, eligible)
    assert len(rows) == 5 and {eligible - 2, eligible - 1} <= set(rows.tolist())
    bow, _ = detector.index.scores(orb.words_of(query), below=eligible)
    others = sorted(set(rows.tolist()) - {eligible - 2, eligible - 1})
    rest = np.delete(bow, rows)
    assert min(bow[others]) >= rest.max()
    candidates = detector.query(len(features) - 1, descriptor=query)
    assert orb.verified[-1] == 5 and len(candidates) == 3
    assert {c.match for c in candidates} <= set(rows.tolist())
    assert all(a.score >= b.score for a, b in zip(candidates, candidates[1:]))
    small = detector.shortlisted(query, 4)  # a small database is verified entirely
    np.testing.assert_array_equal(small, np.arange(4))
    with pytest.raises(ValueError, match="recent"):
        LoopDetector(orb, shortlist=2, recent=3)


def test_loop_closer_state_keeps_the_index_and_shares_the_pnp_features(icl_frames):
    cfg = LoopConfig(exclusion_frames=4, shortlist=4, recent_candidates=1)
    closer = LoopCloser(cfg, depth_points=DepthKeyframePoints())
    for n in range(0, 24, 2):
        closer.detector.add(n, icl_frames[n].image)
        closer.pnp.add_keyframe(n, icl_frames[n].image, closer.detector.descriptor_of(n))
    state = unpack(pack(closer.state_dict()))
    assert all(f == {"kind": "detector"} for f in state["pnp_features"])
    assert all(e["words"].dtype == np.uint16 for e in state["entries"])
    restored = LoopCloser(cfg, depth_points=DepthKeyframePoints())
    restored.load_state_dict(state)
    assert restored.detector.indices == closer.detector.indices
    assert restored.pnp.features[4] is restored.detector.descriptor_of(4)
    query = OrbDescriptor().describe(icl_frames[30].image)
    a = closer.detector.query(30, descriptor=query)
    b = restored.detector.query(30, descriptor=query)
    assert a and a == b
