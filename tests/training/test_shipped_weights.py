"""The default model's weights ship in the repository: they load strictly, SlamConfig picks them up, and they are
trained (better depth than a random model on a held-out synthetic scene)."""

import torch
from safetensors import safe_open

from worker.config import DEFAULT_CHECKPOINT, SlamConfig
from worker.frontend import build_model
from worker.frontend.checkpoint import load_checkpoint
from worker.training.evaluate import evaluate_model, held_out_synthetic


def test_shipped_tiny_weights_match_the_tiny_model():
    assert DEFAULT_CHECKPOINT.is_file(), f"{DEFAULT_CHECKPOINT} is missing"
    assert DEFAULT_CHECKPOINT.stat().st_size <= 50 * 2**20
    expected = build_model("tiny", device="meta").state_dict()
    with safe_open(str(DEFAULT_CHECKPOINT), framework="pt") as f:
        keys = set(f.keys())
        assert keys == set(expected)
        for key in keys:
            assert tuple(f.get_slice(key).get_shape()) == tuple(expected[key].shape), key
    model = load_checkpoint(DEFAULT_CHECKPOINT)
    assert model.config.name == "tiny"
    assert all(p.dtype == torch.float32 and torch.isfinite(p).all() for p in model.parameters())


def test_slam_config_defaults_to_the_shipped_weights():
    assert SlamConfig().checkpoint_path() == DEFAULT_CHECKPOINT
    assert SlamConfig.preset("fast").checkpoint_path() == DEFAULT_CHECKPOINT
    assert SlamConfig.from_dict({"frontend": {"model": "small"}}).checkpoint_path() is None


def test_shipped_weights_beat_a_random_model_on_held_out_depth():
    torch.set_num_threads(min(2, torch.get_num_threads()))
    seq = held_out_synthetic(1, frames=3)[0]
    trained = evaluate_model(load_checkpoint(DEFAULT_CHECKPOINT), seq)
    torch.manual_seed(0)
    untrained = evaluate_model(build_model("tiny"), seq)
    assert trained.abs_rel < 0.5
    assert not trained.abs_rel >= untrained.abs_rel  # a random model's depth may be all invalid (NaN)
    assert trained.psnr > untrained.psnr + 2.0
