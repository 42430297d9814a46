"""Frames with poses and no depth (a phone without a depth sensor): keyframe surfels come from multi-view stereo on
the tracked poses (worker.pipeline.depth_sources.multiview), computed in the mapping stage once later frames give each
keyframe neighbours; real ICL frames (tests/data/icl_mini), metric depth against the dataset's."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from posed_rgb_run import run_posed_rgb

from worker.config import SlamConfig
from worker.data import open_source
from worker.slam import SlamSystem

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def posed_rgb():
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=True, max_frames=14)
    frames = list(src)
    truth = [f.depth for f in frames]
    for f in frames:
        f.depth = None  # the engine sees poses and images only
    return frames, truth, src.intrinsics


def _config() -> SlamConfig:
    return SlamConfig.preset("rgbd", threaded=False, input={"pose_mode": "fixed"},
                             mapping={"refine_iterations": 1, "final_refine_passes": 0})


def test_posed_rgb_keyframes_are_mapped_from_multiview_depth(posed_rgb) -> None:
    frames, truth, intr = posed_rgb
    system = SlamSystem(_config(), intr)
    results = [system.push(f) for f in frames]
    assert system.depth_source == "mvs" and system.tracker is None  # no model anywhere
    system.finish()
    keyframes = [i for i, r in enumerate(results) if r.is_keyframe]
    final = [] if system.last_frame_mapped is None else [system.last_frame_mapped]  # finish maps the last view
    assert len(keyframes) >= 2 and system.mapping_stage.keyframes_mapped == len(keyframes) + len(final)
    assert system.timings.counts["map_depth"] == len(keyframes) + len(final)
    assert system.num_gaussians > 2000
    k = keyframes[1]  # a keyframe with neighbours on both sides
    _, depth = system.render_view(frames[k].pose, intr.matrix(), intr.width, intr.height)
    covered = (depth > 0) & (truth[k] > 0)
    assert covered.mean() > 0.5
    assert float(np.median(np.abs(depth[covered] - truth[k][covered]))) < 0.05  # metres, on real images
    system.close()


def test_stereo_keyframes_are_pruned_where_sensor_keyframes_are_not(posed_rgb) -> None:
    """The rgbd preset keeps pruning off (it cut holes in sensor maps); a session whose keyframe depth comes from
    multi-view stereo prunes (`prune_multiview`) and keeps a background behind its map (`background`), restored
    from a snapshot too, unless the config says no; a sensor-depth session does neither."""
    frames, truth, intr = posed_rgb

    def prunes(system: SlamSystem) -> bool:
        thresholds = system.mapping_stage.map.config.thresholds
        return math.isfinite(thresholds.rgb_error) and math.isfinite(thresholds.depth_error)

    stereo = SlamSystem(_config(), intr)
    assert not prunes(stereo)  # nothing known about the session's depth before its first frame
    assert not stereo.mapping_stage.map.keeps_background
    stereo.push(frames[0])
    assert stereo.depth_source == "mvs" and prunes(stereo) and stereo.mapping_stage.map.keeps_background
    restored = SlamSystem.restore(stereo.snapshot())
    assert prunes(restored) and restored.mapping_stage.map.keeps_background
    sensor = SlamSystem(_config(), intr)
    sensor.push(dataclasses.replace(frames[0], depth=truth[0]))
    assert sensor.depth_source == "sensor" and not prunes(sensor) and not sensor.mapping_stage.map.keeps_background
    declined = SlamSystem(_config().model_copy(update={"mapping": _config().mapping.model_copy(
        update={"prune_multiview": False, "background": False})}), intr)
    declined.push(frames[0])
    assert declined.depth_source == "mvs" and not prunes(declined) and not declined.mapping_stage.map.keeps_background
    for system in (stereo, restored, sensor, declined):
        system.close()


def test_snapshot_keeps_keyframes_waiting_for_neighbours(posed_rgb) -> None:
    frames, _, intr = posed_rgb
    first = SlamSystem(_config(), intr)
    for f in frames[:8]:
        first.push(f)
    waiting = len(first.tracking_stage.depth_source.waiting)
    assert waiting >= 1  # the last keyframe still waits for later frames
    restored = SlamSystem.restore(first.snapshot())
    assert len(restored.tracking_stage.depth_source.waiting) == waiting
    for f in frames[8:]:
        restored.push(f)
    restored.finish()
    mapped = restored.mapping_stage.keyframes_mapped
    assert mapped == len(restored.trajectory("keyframes")) + (restored.last_frame_mapped is not None)
    restored.close()
    first.close()


def test_the_model_can_fill_what_stereo_leaves_empty(posed_rgb) -> None:
    frames, _, intr = posed_rgb
    counts = {}
    for fill in ("none", "model"):
        system = run_posed_rgb(frames, intr, fill)
        counts[fill] = system.num_gaussians
        assert (system.model is not None) == (fill == "model") and system.tracker is None
        system.close()
    assert counts["model"] > 1.2 * counts["none"]  # the pixels stereo could not match get surfels too
