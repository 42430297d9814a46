"""bench.held_out: labelled repeats of a mode are summarised on the frames every run held out."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.held_out import main


def _run(folder: Path, index: list[int], psnr: list[float]) -> str:
    folder.mkdir()
    held = {"index": index, "psnr": psnr, "psnr_normalised": psnr}
    (folder / "metrics.json").write_text(json.dumps(
        {"mode": "posed", "eval_frames": len(index), "psnr": sum(psnr) / len(psnr),
         "psnr_normalised": sum(psnr) / len(psnr), "held_out": held}))
    return str(folder)


def test_labelled_runs_get_mean_and_spread_on_common_frames(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # frame 9 is held out by one run only: it must not count in anyone's common mean
    a1 = _run(tmp_path / "a1", [1, 2, 9], [20.0, 22.0, 40.0])
    a2 = _run(tmp_path / "a2", [1, 2], [22.0, 24.0])
    b1 = _run(tmp_path / "b1", [1, 2], [10.0, 12.0])
    assert main([f"posed={a1}", f"posed={a2}", f"unposed={b1}"]) == 0
    out = capsys.readouterr().out
    assert "2 frames held out by all 3 runs" in out
    assert "posed: 2 runs, common frames 22.000 +- 1.414 dB (min 21.00, max 23.00)" in out
    assert "unposed: 1 runs, common frames 11.000 +- 0.000 dB" in out


def test_unlabelled_runs_print_no_groups(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    a = _run(tmp_path / "a", [1], [20.0])
    b = _run(tmp_path / "b", [1], [21.0])
    assert main([a, b]) == 0
    out = capsys.readouterr().out
    assert "1 frames held out by all 2 runs" in out and "+-" not in out
