"""safetensors checkpoints of our model: round trip, stored config and metadata, clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from frontend_test_config import TEST_CONFIG, single_torch_thread  # noqa: F401
from safetensors.torch import save_file

from worker.frontend import build_model
from worker.frontend.checkpoint import load_checkpoint, read_checkpoint_metadata, save_checkpoint


def test_round_trip_restores_identical_outputs(tmp_path: Path) -> None:
    model = build_model(TEST_CONFIG)
    path = save_checkpoint(model, tmp_path / "m.safetensors", {"stage": 2, "note": "unit"})
    assert path.read_bytes()[:8] != b"PK\x03\x04"  # not a zip/pickle
    loaded = load_checkpoint(path)
    assert loaded.config == TEST_CONFIG
    assert loaded.checkpoint_metadata == {"stage": 2, "note": "unit"}
    image = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        a = model.step(image, model.init_state())
        b = loaded.step(image, loaded.init_state())
    assert torch.equal(a.points_cam, b.points_cam) and torch.equal(a.scales, b.scales)


def test_named_config_is_stored(tmp_path: Path) -> None:
    path = save_checkpoint(build_model("tiny"), tmp_path / "tiny.safetensors")
    config, meta = read_checkpoint_metadata(path)
    assert config.name == "tiny" and meta == {}
    assert load_checkpoint(path).config.name == "tiny"


def test_non_json_metadata_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="JSON"):
        save_checkpoint(build_model(TEST_CONFIG), tmp_path / "x.safetensors", {"bad": object()})


def test_foreign_and_missing_files_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not found"):
        load_checkpoint(tmp_path / "nope.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="not a safetensors"):
        load_checkpoint(junk)
    plain = tmp_path / "plain.safetensors"
    save_file({"w": torch.zeros(2)}, str(plain))
    with pytest.raises(ValueError, match="no Flash-Mono frontend configuration"):
        load_checkpoint(plain)


def test_tensors_not_matching_the_config_are_rejected(tmp_path: Path) -> None:
    path = save_checkpoint(build_model(TEST_CONFIG), tmp_path / "m.safetensors")
    from safetensors.torch import load_file

    tensors = load_file(str(path))
    _, _ = read_checkpoint_metadata(path)
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        header = f.metadata()
    del tensors["pose_token"]
    broken = tmp_path / "broken.safetensors"
    save_file(tensors, str(broken), metadata=header)
    with pytest.raises(ValueError, match="pose_token"):
        load_checkpoint(broken)
