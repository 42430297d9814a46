"""What the mapping processes' fork server imports once, so that no session's mapping process pays for it (see
worker.runtime.engine.warm_up for the same in a worker): the mapping side, the compiled kernels, and the optimiser,
whose first use imports torch's compiler stack for ~2 s. No tensor work runs here: a process forked after torch's
thread pool started would inherit a broken pool."""

from __future__ import annotations

import importlib

import torch

from worker.pipeline.mapping_process import child  # noqa: F401 - loaded before any fork

for _kernels in ("worker.mapping.raster_cpu", "worker.depth.mvs_cpu"):
    importlib.import_module(_kernels).available()
torch.optim.Adam([torch.zeros(1, requires_grad=True)])
