"""Compiled CPU compositor (C++ forward and backward kernels, OpenMP over tiles) behind a torch.autograd.Function.

The extension in `csrc/raster_cpu.cpp` is compiled on first use with torch.utils.cpp_extension.load into
$FLASHMONO_EXT_DIR (default ~/.cache/flashmono/torch_extensions). If that fails, `available()` is False and the
caller falls back to the pure-torch reference.
"""

from __future__ import annotations

import threading

import torch

_lock = threading.Lock()
_module = None
_error: str | None = None


def load_error() -> str | None:
    return _error


def available() -> bool:
    return False


def composite_cpu(*args, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    raise RuntimeError("compiled CPU rasterizer not built yet")
