"""bench.refine: the end-of-run pass (`--final`) runs after the keyframe refinements and improves the keyframes."""

from __future__ import annotations

import re

import pytest

from bench.refine import main


def test_the_final_pass_is_timed_and_raises_the_keyframes_psnr(capsys: pytest.CaptureFixture) -> None:
    assert main(["--keyframes", "2", "--iterations", "2", "--final", "12", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    found = re.search(r"final refinement: 12 iterations over 2 keyframes in ([\d.]+) s .* mean PSNR ([\d.]+) -> "
                      r"([\d.]+) dB", out)
    assert found, out
    seconds, before, after = (float(v) for v in found.groups())
    assert seconds > 0
    # two refinement steps per keyframe leave plenty for twelve more to fit
    assert after > before
