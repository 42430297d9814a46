"""Fixtures for the loop-closure tests: the ICL mini frames (downscaled to 160x120) and their overlap oracle."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from worker.loop.oracle import load_rgbd_folder


@pytest.fixture(scope="session")
def icl_frames(request):
    return load_rgbd_folder(Path(request.config.rootpath) / "tests" / "data" / "icl_mini", downscale=2)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """These tests run many small tensor ops, where a 2-thread pool on a shared 2-core machine mostly waits."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
