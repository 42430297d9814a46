"""Import a CUT3R checkpoint (`torch.save({"model": state_dict, "args": ...})`, zip format) without running pickle code.

`read_cut3r_state_dict` parses the archive's data.pkl with a restricted unpickler: only the few globals such a file
holds are resolved (tensor rebuild functions, storage types, OrderedDict, defaultdict, argparse.Namespace, plain
builtin types, also under their Python 2 names such as `__builtin__.long`, which protocol-2 pickles carry); OmegaConf
objects (CUT3R's `args`) become inert placeholders; anything else is refused with an error naming the global.
`map_cut3r_state_dict` renames CUT3R keys to ours (identical except the RGB DPT, which becomes the 2DGS DPT).
"""

from __future__ import annotations

import argparse
import builtins
import collections
import pickle
import re
import zipfile
from pathlib import Path

import torch

from .checkpoint import save_checkpoint
from .configs import GAUSSIAN_CHANNELS
from .model import FeedForwardModel, build_model


class UnsafeCheckpointError(ValueError):
    """The checkpoint references a Python global outside the allow-list."""


_STORAGE_DTYPES = {
    "FloatStorage": torch.float32, "DoubleStorage": torch.float64, "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16, "LongStorage": torch.int64, "IntStorage": torch.int32,
    "ShortStorage": torch.int16, "CharStorage": torch.int8, "ByteStorage": torch.uint8, "BoolStorage": torch.bool,
    "UntypedStorage": torch.uint8,
}
_SAFE_BUILTINS = {"dict", "list", "tuple", "set", "frozenset", "int", "float", "str", "bytes", "bool", "complex"}
# Python 2 names of safe builtins, as protocol-2 pickles (torch.save's default) write them: module __builtin__.
_PY2_BUILTIN_NAMES = {"long": "int", "unicode": "str"}
_SAFE_COLLECTIONS = {"OrderedDict": collections.OrderedDict, "defaultdict": collections.defaultdict}
_INERT_MODULE_PREFIXES = ("omegaconf", "typing")


class _StorageType:
    def __init__(self, dtype: torch.dtype) -> None:
        self.dtype = dtype


class SkippedObject:
    """Stands in for an object we refuse to reconstruct (OmegaConf configs): accepts any arguments, does nothing."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def __setstate__(self, state) -> None:
        pass


def _rebuild_tensor(storage: torch.Tensor, offset: int, size, stride, requires_grad=False, hooks=None,
                    metadata=None) -> torch.Tensor:
    return torch.as_strided(storage, tuple(size), tuple(stride), offset)


def _rebuild_parameter(data: torch.Tensor, requires_grad=False, hooks=None, *args) -> torch.Tensor:
    return data


class RestrictedUnpickler(pickle.Unpickler):
    """Resolves only allow-listed globals; tensors are rebuilt by our own code from the archive's storages."""

    def __init__(self, file, read_storage) -> None:
        super().__init__(file)
        self._read_storage = read_storage
        self._storages: dict[str, torch.Tensor] = {}

    def find_class(self, module: str, name: str):
        if module == "torch._utils" and name == "_rebuild_tensor_v2":
            return _rebuild_tensor
        if module == "torch._utils" and name == "_rebuild_parameter":
            return _rebuild_parameter
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(_STORAGE_DTYPES[name])
        if module == "collections" and name in _SAFE_COLLECTIONS:
            return _SAFE_COLLECTIONS[name]
        if module == "argparse" and name == "Namespace":
            return argparse.Namespace
        if module == "__builtin__":
            module, name = "builtins", _PY2_BUILTIN_NAMES.get(name, name)
        if module == "builtins" and name in _SAFE_BUILTINS:
            return getattr(builtins, name)
        if module.split(".")[0] in _INERT_MODULE_PREFIXES:
            return SkippedObject
        raise UnsafeCheckpointError(f"refusing to unpickle global {module}.{name}: not in the checkpoint allow-list")

    def persistent_load(self, pid):
        if not isinstance(pid, tuple) or len(pid) < 5 or pid[0] != "storage":
            raise UnsafeCheckpointError(f"unexpected persistent id {pid!r:.80}")
        storage_type, key = pid[1], str(pid[2])
        if not isinstance(storage_type, _StorageType):
            raise UnsafeCheckpointError(f"unexpected storage type {storage_type!r:.80}")
        if key not in self._storages:
            raw = bytearray(self._read_storage(key))
            self._storages[key] = torch.frombuffer(raw, dtype=storage_type.dtype) if raw else torch.empty(
                0, dtype=storage_type.dtype)
        return self._storages[key]


def read_torch_zip(path: str | Path):
    """Unpickle a torch.save zip archive with the restricted unpickler; returns the saved object."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint not found: {path}")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path} is not a torch zip checkpoint (legacy or foreign formats are not supported)")
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        pkl = [n for n in names if n.endswith("/data.pkl") or n == "data.pkl"]
        if len(pkl) != 1:
            raise ValueError(f"{path}: expected one data.pkl in the archive, found {len(pkl)}")
        prefix = pkl[0][: -len("data.pkl")]
        byteorder = prefix + "byteorder"
        if byteorder in names and archive.read(byteorder).decode().strip() != "little":
            raise ValueError(f"{path}: big-endian checkpoints are not supported")
        with archive.open(pkl[0]) as f:
            return RestrictedUnpickler(f, lambda key: archive.read(f"{prefix}data/{key}")).load()


def read_cut3r_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """The `model` state dict of a CUT3R checkpoint (its `args` are never reconstructed)."""
    obj = read_torch_zip(path)
    if isinstance(obj, dict) and "model" in obj:
        obj = obj["model"]
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise ValueError(f"{path}: no state dict found (expected a dict with a 'model' entry of tensors)")
    return {str(k).removeprefix("module."): v for k, v in obj.items()}


_ALIAS = re.compile(r"^(downstream_head\.dpt_\w+\.scratch)\.layer_rn\.(\d)\.weight$")
_RGB_PREFIX = "downstream_head.dpt_rgb."
_GS_PREFIX = "downstream_head.dpt_gs."
# Keys that exist only in Flash-Mono (left at their fresh initialisation on import).
NEW_KEY_PREFIXES = ("downstream_head.gs_adapter.",)


def map_cut3r_state_dict(cut3r: dict[str, torch.Tensor],
                         expected: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], list[str]]:
    """Rename a CUT3R-512 state dict to our keys. Returns (mapped state, keys left freshly initialised).

    Drops the aliased DPT convs (scratch.layer_rn.{0..3} == scratch.layer{1..4}_rn), copies the image decoder into
    the state decoder when a checkpoint lacks it, and turns the RGB DPT into the 2DGS DPT: its colour output rows
    come from CUT3R, the opacity/rotation/scale rows start at zero (opacity 0.5, identity rotation, pixel-footprint
    scale). Raises ValueError on unexpected keys, missing keys or shape mismatches.
    """
    state = dict(cut3r)
    for key in list(state):
        match = _ALIAS.match(key)
        if match:
            canonical = f"{match.group(1)}.layer{int(match.group(2)) + 1}_rn.weight"
            alias = state.pop(key)
            state.setdefault(canonical, alias)
    if not any(k.startswith("dec_blocks_state.") for k in state):
        for key in [k for k in state if k.startswith("dec_blocks.")]:
            state["dec_blocks_state." + key[len("dec_blocks."):]] = state[key]
    for key in [k for k in state if k.startswith(_RGB_PREFIX)]:
        state[_GS_PREFIX + key[len(_RGB_PREFIX):]] = state.pop(key)
    for name in ("weight", "bias"):
        key = f"{_GS_PREFIX}head.4.{name}"
        if key in state and key in expected and state[key].shape != expected[key].shape:
            rgb = state[key]
            widened = torch.zeros((GAUSSIAN_CHANNELS,) + tuple(rgb.shape[1:]), dtype=rgb.dtype)
            widened[: rgb.shape[0]] = rgb
            state[key] = widened

    unexpected = sorted(set(state) - set(expected))
    missing = sorted(set(expected) - set(state))
    fresh = [k for k in missing if k.startswith(NEW_KEY_PREFIXES)]
    missing = [k for k in missing if not k.startswith(NEW_KEY_PREFIXES)]
    if unexpected or missing:
        raise ValueError(f"not a CUT3R-512 checkpoint for this config: {len(unexpected)} unexpected keys "
                         f"{unexpected[:5]}, {len(missing)} missing keys {missing[:5]}")
    for key, value in state.items():
        if tuple(value.shape) != tuple(expected[key].shape):
            raise ValueError(f"{key}: checkpoint shape {tuple(value.shape)} != model {tuple(expected[key].shape)}")
    return state, fresh


def load_cut3r_into(model: FeedForwardModel, path: str | Path) -> list[str]:
    """Load a CUT3R checkpoint into `model` in place; returns the keys left at their fresh initialisation."""
    state, fresh = map_cut3r_state_dict(read_cut3r_state_dict(path), model.state_dict())
    model.load_state_dict(state, strict=False)
    return fresh


def convert_cut3r_checkpoint(source: str | Path, target: str | Path, config: str = "paper") -> list[str]:
    """Convert a CUT3R-512 .pth into our safetensors checkpoint of the given config; returns the fresh keys."""
    state, fresh = map_cut3r_state_dict(read_cut3r_state_dict(source), build_model(config, "meta").state_dict())
    model = build_model(config)
    model.load_state_dict(state, strict=False)
    save_checkpoint(model, target, {"source": "cut3r", "source_file": Path(source).name, "fresh_keys": fresh})
    return fresh
