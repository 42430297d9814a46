"""Benchmarks run by these tests write their result records to a temporary folder, never to bench/results/."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.record import RESULTS_ENV


@pytest.fixture(autouse=True)
def bench_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = tmp_path / "bench-results"
    monkeypatch.setenv(RESULTS_ENV, str(folder))
    return folder
