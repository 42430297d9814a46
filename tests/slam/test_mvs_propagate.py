"""Posed RGB without depth, `input.mvs_fill: propagate`: keyframe pixels stereo leaves without depth get surfels
from depth propagated along their surface (worker.depth.hole_fill), starting less opaque; real ICL frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from posed_rgb_run import run_posed_rgb

from worker.data import open_source
from worker.pipeline.depth_sources.multiview import PROPAGATED_OPACITY
from worker.pipeline.surfel_init import INITIAL_OPACITY

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def posed_rgb():
    src = open_source(str(DATA), use_gt_depth=False, use_gt_poses=True, max_frames=10)
    return list(src), src.intrinsics


def test_propagated_depth_adds_fainter_surfels_where_stereo_left_holes(posed_rgb) -> None:
    frames, intr = posed_rgb
    plain, filled = run_posed_rgb(frames, intr, "none"), run_posed_rgb(frames, intr, "propagate")
    stats = filled.mapping_stage.stereo.fill_stats
    assert stats and min(stats) > 0.01 and not plain.mapping_stage.stereo.fill_stats
    assert filled.num_gaussians > 1.03 * plain.num_gaussians
    opacities = filled.mapping_stage.map.surfels.opacities.numpy()
    # the propagated pixels' surfels (merged 2x2 blocks among them) start below the usual opacity
    assert np.isclose(opacities, INITIAL_OPACITY * PROPAGATED_OPACITY, atol=1e-3).sum() > 100
    assert np.isclose(opacities, INITIAL_OPACITY, atol=1e-3).sum() > 0.5 * len(opacities)
    plain.close()
    filled.close()
