"""The released CUT3R checkpoints pickle their Hydra `args` as a real OmegaConf DictConfig; with torch.save's
protocol 2 its globals include `__builtin__.dict`, `__builtin__.long` and `collections.defaultdict`. The restricted
unpickler reads such a file (mapping the Python 2 names) and still refuses every global that could run code."""

from __future__ import annotations

import pickletools
import zipfile
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from worker.frontend.cut3r_import import UnsafeCheckpointError, read_cut3r_state_dict, read_torch_zip


def _globals(path: Path) -> set[str]:
    with zipfile.ZipFile(path) as archive:
        data = archive.read(next(n for n in archive.namelist() if n.endswith("data.pkl")))
    return {str(arg) for op, arg, _ in pickletools.genops(data) if op.name == "GLOBAL"}


def test_checkpoint_with_a_real_omegaconf_args_is_read(tmp_path: Path) -> None:
    args = OmegaConf.create({"model": "ARCroco3DStereo(...)", "lr": 1e-4, "epochs": 2**40, "dims": [512, 768],
                             "train": {"batch": 4, "accum": None}})
    weights = {"enc.weight": torch.arange(6.0).reshape(2, 3), "enc.bias": torch.tensor([1, 2], dtype=torch.int64)}
    path = tmp_path / "cut3r_512_dpt_4_64.pth"
    torch.save({"model": weights, "args": args, "epoch": 3}, path)
    assert {"__builtin__ dict", "__builtin__ long", "collections defaultdict"} <= _globals(path)
    state = read_cut3r_state_dict(path)
    assert set(state) == set(weights)
    assert all(torch.equal(state[k], v) for k, v in weights.items())


class _Reduces:
    """Pickles as a call of `target(*args)`: what a malicious checkpoint does."""

    def __init__(self, target, args) -> None:
        self.target, self.args = target, args

    def __reduce__(self):
        return self.target, self.args


@pytest.mark.parametrize("target", [eval, exec, getattr, __import__, compile])
def test_python2_builtin_names_that_run_code_are_still_refused(tmp_path: Path, target) -> None:
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pth"
    torch.save({"model": {}, "args": _Reduces(target, (f"open({str(marker)!r}, 'w')",))}, path)
    assert f"__builtin__ {target.__name__}" in _globals(path)  # written under the Python 2 module name
    with pytest.raises(UnsafeCheckpointError, match=target.__name__):
        read_torch_zip(path)
    assert not marker.exists()
