"""The map does not depend on the scene's units: real frames with their poses in metres, in 5 cm units or in 20 m
units (`open_source(..., scale=s)`) give the same keyframes and the same renders (worker.geometry.scene_units)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.eval.metrics import psnr
from worker.slam import SlamSystem

ICL_MINI = Path(__file__).parents[1] / "data" / "icl_mini"
SIZE = (80, 60)


def posed_rgb_map(scale: float) -> tuple[list[int], float, float | None]:
    """Posed RGB (multi-view stereo on the given poses) over the first 24 frames of ICL (every third frame of the
    sequence) in units of 1/scale metres: (keyframes, mean PSNR of the other frames rendered from the map, the
    pose graph's length unit)."""
    source = open_source(ICL_MINI, max_frames=24, resize=SIZE, use_gt_poses=True, use_gt_depth=False, scale=scale)
    config = SlamConfig.preset("rgbd", threaded=False, mapping={"refine_iterations": 5, "final_refine_passes": 2})
    system = SlamSystem(config, source.intrinsics)
    try:
        frames = list(source)
        for frame in frames:
            system.push(frame)
        system.finish()  # (24 frames: the device poses are still judged; finish decides and maps them)
        keyframes = [index for index, _, _ in system.trajectory("keyframes")]
        K = source.intrinsics.matrix().numpy()
        poses = {index: pose for index, _, pose in system.trajectory("all")}
        scores = [psnr(system.render_view(poses[f.index], K, *SIZE)[0], f.image) for f in frames
                  if f.index not in keyframes]
        return keyframes, float(np.mean(scores)), system.pose_graph.length_unit
    finally:
        system.close()


def test_posed_rgb_maps_the_same_scene_alike_in_any_units() -> None:
    keyframes, reference, unit = posed_rgb_map(1.0)
    assert reference > 24.0 and 4 <= len(keyframes) <= 12
    assert unit == pytest.approx(2.0, rel=0.2)  # ICL's first estimated keyframe: 2 m away
    for scale in (0.05, 20.0):
        # before, a keyframe every 0.2 pose units until a depth was known: 6 keyframes in metres (27.77 dB), 5 in
        # 20 m units (x0.05, 27.08 dB), 9 in 5 cm units (x20, 27.52 dB)
        same_keyframes, score, scaled_unit = posed_rgb_map(scale)
        assert same_keyframes == keyframes
        assert score == pytest.approx(reference, abs=0.1)
        assert scaled_unit == pytest.approx(unit * scale, rel=1e-3)


def test_a_scaled_source_scales_poses_and_depth_only() -> None:
    plain = next(iter(open_source(ICL_MINI, max_frames=2, use_gt_poses=True, stride=5)))
    scaled = next(iter(open_source(ICL_MINI, max_frames=2, use_gt_poses=True, stride=5, scale=0.1)))
    assert np.array_equal(scaled.image, plain.image) and scaled.intrinsics == plain.intrinsics
    assert np.allclose(scaled.depth, 0.1 * plain.depth)
    for got, want in ((scaled.pose, plain.pose), (scaled.gt_pose, plain.gt_pose)):
        assert np.allclose(got[:3, :3], want[:3, :3]) and np.allclose(got[:3, 3], 0.1 * want[:3, 3])
    with pytest.raises(ValueError, match="scale"):
        open_source(ICL_MINI, scale=-1.0)
