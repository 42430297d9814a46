"""`python -m bench vo_scale` on real ICL frames: the odometry's units per reference unit and the scene's own scale in
its units are measured at each keyframe and both hold (the odometry keeps its scale on this sequence)."""

from __future__ import annotations

import json

import numpy as np

from bench import vo_scale


def test_both_scales_hold_on_icl_and_the_figures_are_written(tmp_path) -> None:
    out = tmp_path / "vo_scale.json"
    assert vo_scale.main(["--frames", "30", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = result["keyframes"]
    assert len(rows) >= 5
    scales = np.array([r["units_per_reference_unit"] for r in rows])
    heights = np.array([r["ground_height_units"] for r in rows])
    assert np.all(scales > 0) and np.all(np.abs(scales / np.median(scales) - 1) < 0.15)
    assert np.all(np.abs(heights / np.median(heights) - 1) < 0.15)
    assert abs(result["step_growth"] - 1) < 0.15 and result["ate_sim3"] < 0.02
