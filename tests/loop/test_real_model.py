"""The real `tiny` frontend model end to end through the tracker, the bag, the encoder descriptor and the
hidden-state relocalization (untrained weights: this checks the plumbing, shapes and contracts, not accuracy)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from worker.frontend import build_model
from worker.frontend.preprocess import prepare_image
from worker.frontend.tracker import SubmapTracker, TrackerConfig
from worker.loop.bag import HiddenStateBag
from worker.loop.descriptors import EncoderGeMDescriptor
from worker.loop.detector import LoopDetector
from worker.loop.relocalize import HiddenStateRelocalizer


@pytest.fixture(scope="module")
def prepared(request):
    folder = Path(request.config.rootpath) / "tests" / "data" / "icl_mini" / "rgb"
    files = sorted(folder.glob("*.jpg"))[:7]
    rgb = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]
    return [prepare_image(im, long_side=128).tensor for im in rgb]


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_model("tiny").eval()


def test_tiny_model_tracks_in_submaps_and_relocalizes(model, prepared):
    tracker = SubmapTracker(model, TrackerConfig(submap_length=3))
    bag = HiddenStateBag()
    tracked = [tracker.track(n, image) for n, image in enumerate(prepared)]
    bag.add_finished(tracker.pop_finished_submaps())
    H, W = prepared[0].shape[2:]
    assert [t.submap_id for t in tracked] == [0, 0, 1, 1, 2, 2, 3]
    assert len(bag) == 3 and bag.submap_of(0) == 0 and bag.submap_of(2) == 1
    for t in tracked:
        assert t.surfels.points.shape == (H, W, 3) and t.surfels.quats.shape == (H, W, 4)
        assert torch.isfinite(t.pose_world).all()
    assert all(np.isfinite(s) and s > 0 for s in tracker.overlap_scales)
    restored = HiddenStateBag.from_bytes(bag.to_bytes())
    assert restored.entry(0).state.state_tokens.shape == bag.entry(0).state.state_tokens.shape
    # relocalize the current submap's first keyframe (6) in submap 0 with its cached state, read-only
    relocalizer = HiddenStateRelocalizer(model, restored, tracker)
    cached = restored.entry(0).state.state_tokens.clone()
    c = relocalizer.relocalize(0, 6, prepared[6])  # no intrinsics: focal estimated from the point map
    assert torch.equal(restored.entry(0).state.state_tokens, cached)
    assert c.i == 0 and c.j == 6 and np.isfinite(c.relative).all() and c.scale > 0
    assert 0.0 <= c.support <= 1.0 and c.reason


def test_encoder_gem_descriptor_is_a_unit_vector_and_ranks_itself_first(model, prepared):
    descriptor = EncoderGeMDescriptor(model)
    d = [descriptor.describe(image) for image in prepared]
    assert d[0].shape == (2 * model.config.enc_dim,)
    assert float(d[0].norm()) == pytest.approx(1.0, abs=1e-5)
    assert torch.allclose(descriptor.describe(prepared[0]), d[0], atol=1e-6)
    scores = descriptor.similarities(d[3], d)
    assert int(np.argmax(scores)) == 3 and scores[3] == pytest.approx(1.0, abs=1e-5)
    detector = LoopDetector(descriptor, exclusion_window=2, top_k=2, min_score=0.0)
    for n, image in enumerate(prepared[:6]):
        candidates = detector.detect(n, image)
        assert all(c.match < n - 2 for c in candidates) and len(candidates) <= 2
    with pytest.raises(ValueError, match="GeM power"):
        EncoderGeMDescriptor(model, p=0.5)
