"""LPIPS is computed only from weights on disk; otherwise it reports why not."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worker.eval import Lpips
from worker.eval.lpips import BACKBONE_FILE, HEADS_FILE, AlexNetFeatures


def test_missing_backbone_gives_none_and_a_reason(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    metric = Lpips.load()
    assert not metric.available
    assert "not available" in metric.reason and BACKBONE_FILE in metric.reason
    assert metric(np.zeros((8, 8, 3)), np.ones((8, 8, 3))) is None


def test_missing_heads_gives_a_reason(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    (tmp_path / "checkpoints").mkdir()
    torch.save(AlexNetFeatures().state_dict(), tmp_path / "checkpoints" / BACKBONE_FILE)
    metric = Lpips.load()
    assert not metric.available and "linear heads" in metric.reason


@pytest.fixture
def local_weights(tmp_path, monkeypatch):
    """Randomly initialised weights in the torchvision/lpips file formats (mechanics only, not the real numbers)."""
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    (tmp_path / "checkpoints").mkdir()
    torch.manual_seed(0)
    state = AlexNetFeatures().state_dict()
    state["classifier.1.weight"] = torch.zeros(2, 2)  # torchvision files also hold the classifier: ignored
    torch.save(state, tmp_path / "checkpoints" / BACKBONE_FILE)
    heads = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate((64, 192, 384, 256, 256))}
    torch.save(heads, tmp_path / "checkpoints" / HEADS_FILE)
    return tmp_path


def test_lpips_with_local_weights_is_a_distance(local_weights):
    metric = Lpips.load()
    assert metric.available, metric.reason
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (64, 64, 3))
    b = np.clip(a + rng.normal(0, 0.3, a.shape), 0, 1)
    assert metric(a, a) == pytest.approx(0.0, abs=1e-7)
    d_ab = metric(a, b)
    assert d_ab > 0
    assert metric(b, a) == pytest.approx(d_ab, rel=1e-5)
    assert metric(a, np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)) < d_ab


def test_wrong_head_file_is_rejected(local_weights):
    torch.save({"lin0.model.1.weight": torch.rand(1, 3, 1, 1)}, local_weights / "checkpoints" / HEADS_FILE)
    with pytest.raises(ValueError, match="lin0"):
        Lpips.load()
