"""CUT3R checkpoint import: restricted unpickler, key mapping against the real 512 key list, CLI conversion."""

from __future__ import annotations

import argparse
import os
import re
import sys
import types
from pathlib import Path

import pytest
import torch
from frontend_test_config import TEST_CONFIG, single_torch_thread  # noqa: F401

from client.cli import main as cli_main
from worker.frontend import build_model
from worker.frontend.checkpoint import load_checkpoint
from worker.frontend.cut3r_import import (
    UnsafeCheckpointError,
    map_cut3r_state_dict,
    read_cut3r_state_dict,
    read_torch_zip,
)

KEYS_TSV = Path(__file__).parent.parent / "data" / "cut3r" / "cut3r_512_state_dict_keys.tsv"
ALIAS = re.compile(r"^(.*\.scratch)\.layer_rn\.(\d)\.weight$")


def synthetic_cut3r_512() -> dict[str, torch.Tensor]:
    """Every key of the real CUT3R-512 state dict with its shape, each a tiny storage expanded to that shape.

    The aliased DPT convs share the storage of their canonical key, as in the real file.
    """
    state: dict[str, torch.Tensor] = {}
    lines = KEYS_TSV.read_text().splitlines()[1:]
    for i, line in enumerate(lines):
        key, shape, _ = line.split("\t")
        dims = tuple(int(x) for x in shape.strip("()").split(",") if x.strip())
        state[key] = torch.full((1,), float(i)).expand(dims)
    for key in list(state):
        m = ALIAS.match(key)
        if m:
            state[key] = state[f"{m.group(1)}.layer{int(m.group(2)) + 1}_rn.weight"]
    return state


@pytest.fixture(scope="module")
def expected() -> dict[str, torch.Tensor]:
    """The paper model's state dict on the meta device (names and shapes only)."""
    return build_model("paper", device="meta").state_dict()


@pytest.fixture(scope="module")
def cut3r_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cut3r") / "cut3r_512_dpt_4_64.pth"
    args = argparse.Namespace(model="ARCroco3DStereo(...)", seed=0)
    torch.save({"model": synthetic_cut3r_512(), "args": args, "epoch": 3}, path)
    return path


def test_synthetic_checkpoint_is_small_and_holds_1248_keys(cut3r_file: Path) -> None:
    assert cut3r_file.stat().st_size < 2_000_000
    state = read_cut3r_state_dict(cut3r_file)
    assert len(state) == 1248
    assert state["pose_retriever.mem"].shape == (1, 256, 1536)
    assert float(state["enc_norm.weight"][5]) == float(state["enc_norm.weight"][0])


def test_512_keys_map_onto_paper_model_with_only_the_2dgs_adapter_fresh(cut3r_file: Path, expected) -> None:
    cut3r = read_cut3r_state_dict(cut3r_file)
    mapped, fresh = map_cut3r_state_dict(cut3r, expected)
    assert fresh and all(k.startswith("downstream_head.gs_adapter.") for k in fresh)
    assert set(mapped) | set(fresh) == set(expected)
    assert not any(".layer_rn." in k for k in mapped)
    # The 2DGS DPT takes over the RGB DPT: colour rows copied, new rows zero.
    gs_w = mapped["downstream_head.dpt_gs.head.4.weight"]
    assert gs_w.shape == (10, 128, 1, 1)
    assert torch.equal(gs_w[:3], cut3r["downstream_head.dpt_rgb.head.4.weight"])
    assert torch.count_nonzero(gs_w[3:]) == 0
    assert torch.equal(mapped["downstream_head.dpt_gs.head.0.weight"], cut3r["downstream_head.dpt_rgb.head.0.weight"])
    # Everything else is carried by name.
    assert torch.equal(mapped["dec_blocks_state.3.attn.qkv.weight"], cut3r["dec_blocks_state.3.attn.qkv.weight"])


def test_alias_only_names_are_accepted_and_missing_state_decoder_is_copied(expected) -> None:
    cut3r = synthetic_cut3r_512()
    for key in [k for k in cut3r if re.search(r"scratch\.layer\d_rn\.weight$", k)]:
        del cut3r[key]  # keep only the scratch.layer_rn.{0..3} spelling
    for key in [k for k in cut3r if k.startswith("dec_blocks_state.")]:
        del cut3r[key]
    mapped, _ = map_cut3r_state_dict(cut3r, expected)
    assert torch.equal(mapped["downstream_head.dpt_self.scratch.layer4_rn.weight"],
                       cut3r["downstream_head.dpt_self.scratch.layer_rn.3.weight"])
    assert torch.equal(mapped["dec_blocks_state.7.mlp.fc1.weight"], cut3r["dec_blocks.7.mlp.fc1.weight"])


def test_unexpected_and_misshapen_keys_are_refused(expected) -> None:
    cut3r = synthetic_cut3r_512()
    cut3r["downstream_head.proj.fc1.weight"] = torch.zeros(3072, 768)  # a 224 linear-head key
    with pytest.raises(ValueError, match="unexpected"):
        map_cut3r_state_dict(cut3r, expected)
    cut3r = synthetic_cut3r_512()
    cut3r["enc_norm.weight"] = torch.zeros(512)
    with pytest.raises(ValueError, match="enc_norm.weight"):
        map_cut3r_state_dict(cut3r, expected)
    cut3r = synthetic_cut3r_512()
    del cut3r["pose_token"]
    with pytest.raises(ValueError, match="missing"):
        map_cut3r_state_dict(cut3r, expected)


class _RunsShell:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_global_is_refused_without_executing(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pth"
    torch.save({"model": {"x": torch.zeros(2)}, "args": _RunsShell(marker)}, path)
    with pytest.raises(UnsafeCheckpointError, match=r"system"):
        read_torch_zip(path)
    assert not marker.exists()


def test_omegaconf_args_are_skipped_cleanly(tmp_path: Path, monkeypatch) -> None:
    # Pickle an object whose class lives in an 'omegaconf' module, as CUT3R's Hydra args do.
    module = types.ModuleType("omegaconf.dictconfig")

    class DictConfig:
        def __init__(self) -> None:
            self.content = {"model": "ARCroco3DStereo(...)"}

    DictConfig.__module__ = "omegaconf.dictconfig"
    DictConfig.__qualname__ = "DictConfig"
    module.DictConfig = DictConfig
    monkeypatch.setitem(sys.modules, "omegaconf", types.ModuleType("omegaconf"))
    monkeypatch.setitem(sys.modules, "omegaconf.dictconfig", module)
    path = tmp_path / "hydra.pth"
    torch.save({"model": {"w": torch.arange(6.0).reshape(2, 3)}, "args": DictConfig()}, path)
    monkeypatch.undo()
    state = read_cut3r_state_dict(path)
    assert torch.equal(state["w"], torch.arange(6.0).reshape(2, 3))


def test_non_zip_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "junk.pth"
    path.write_bytes(b"\x80\x02not a zip")
    with pytest.raises(ValueError, match="zip"):
        read_cut3r_state_dict(path)


def _as_cut3r(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Our state dict spelled as CUT3R would: RGB DPT with 3 channels and the aliased convs."""
    out = {}
    for key, value in state.items():
        if key.startswith("downstream_head.gs_adapter."):
            continue
        if key.startswith("downstream_head.dpt_gs."):
            key = "downstream_head.dpt_rgb." + key[len("downstream_head.dpt_gs."):]
            if ".head.4." in key:
                value = value[:3]
        out[key] = value.clone()
        m = re.match(r"^(.*\.scratch)\.layer(\d)_rn\.weight$", key)
        if m:
            out[f"{m.group(1)}.layer_rn.{int(m.group(2)) - 1}.weight"] = out[key]
    return out


def test_cli_converts_a_checkpoint_end_to_end(tmp_path: Path, monkeypatch) -> None:
    import worker.frontend.configs as configs

    monkeypatch.setitem(configs.CONFIGS, TEST_CONFIG.name, TEST_CONFIG)
    source_model = build_model(TEST_CONFIG)
    src = tmp_path / "cut3r_like.pth"
    torch.save({"model": _as_cut3r(source_model.state_dict()), "args": argparse.Namespace(model="x")}, src)
    out = tmp_path / "converted.safetensors"
    assert cli_main(["convert-cut3r", str(src), str(out), "--config", TEST_CONFIG.name]) == 0
    model = load_checkpoint(out)
    assert model.checkpoint_metadata["source"] == "cut3r"
    image = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        a = source_model.step(image, source_model.init_state())
        b = model.step(image, model.init_state())
    # Geometry and pose come straight from the CUT3R weights; the colour rows too.
    assert torch.allclose(a.points_cam, b.points_cam, atol=1e-6)
    assert torch.allclose(a.pose_c2w, b.pose_c2w, atol=1e-6)
    assert torch.allclose(a.colors, b.colors, atol=1e-6)


def test_cli_reports_bad_input(tmp_path: Path, capsys) -> None:
    assert cli_main(["convert-cut3r", str(tmp_path / "missing.pth"), str(tmp_path / "o.safetensors")]) == 1
    assert "not found" in capsys.readouterr().err
