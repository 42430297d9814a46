"""Keyframes chosen by the engine follow the scene, not the pose units: parallax and overlap of the last keyframe's
view (its depth, or a plane at the median scene depth known from multi-view stereo); while no depth is known,
only turns and the every-N floor (never a distance in pose units)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import Frame, open_source
from worker.geometry import Intrinsics
from worker.pipeline.keyframes import KeyframeView, MotionKeyframeSelector
from worker.slam import SlamSystem

CAMERA = Intrinsics(160.0, 160.0, 80.0, 60.0, 160, 120)
ICL_MINI = Path(__file__).parents[1] / "data" / "icl_mini"


def pose(x: float = 0.0, z: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """c2w: camera at (x, 0, z), turned `yaw_deg` about its y axis."""
    a = math.radians(yaw_deg)
    out = np.eye(4)
    out[:3, :3] = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    out[:3, 3] = [x, 0.0, z]
    return out


def walk(scale: float, frames: int = 120) -> list[tuple[np.ndarray, np.ndarray]]:
    """A camera sliding sideways, then forward, with a slow pan, in front of a wall `scale` away (each frame's pose
    and depth map): the same motion in any unit."""
    out, x, z = [], 0.0, 0.0
    for k in range(frames):
        if k < frames // 2:
            x += 0.006 * scale
        else:
            z += 0.006 * scale
        depth = np.full((CAMERA.height, CAMERA.width), scale - z, np.float32)
        out.append((pose(x, z, yaw_deg=0.05 * k), depth))
    return out


def flags(selector: MotionKeyframeSelector, sequence, with_depth: bool = True) -> list[bool]:
    return [selector.is_keyframe(p, depth=d if with_depth else None, camera=CAMERA) for p, d in sequence]


def selector(**kwargs) -> MotionKeyframeSelector:
    options = {"every": 1000, "translation": 0.2, "rotation_deg": 15.0, "depth_ratio": 0.06, "min_overlap": 0.7}
    return MotionKeyframeSelector(**(options | kwargs))


def test_the_same_keyframes_at_two_scene_scales() -> None:
    near, far = flags(selector(), walk(0.5)), flags(selector(), walk(20.0))
    assert near == far
    assert 6 <= sum(near) <= 30
    # an absolute distance (the rule before) picks a different number in each unit: the test can fail
    absolute_near, absolute_far = flags(selector(depth_ratio=None), walk(0.5)), flags(selector(depth_ratio=None),
                                                                                        walk(20.0))
    assert sum(absolute_near) < sum(near) < sum(absolute_far)


def test_motion_along_the_view_needs_more_travel_than_sideways() -> None:
    sequence = walk(2.0)
    chosen = flags(selector(), sequence)
    sideways, forward = sum(chosen[:60]), sum(chosen[60:])
    assert sideways >= 2 * forward >= 2
    view = KeyframeView.plane(2.0, CAMERA)
    assert view.parallax(np.array([0.1, 0.0, 0.0])) > 2 * view.parallax(np.array([0.0, 0.0, 0.1]))
    assert view.parallax(np.array([0.1, 0.0, 0.0])) == pytest.approx(0.1 / 2.0, rel=0.15)  # about motion / depth


def test_a_turn_below_the_rotation_limit_that_leaves_the_view_makes_a_keyframe() -> None:
    narrow = Intrinsics(400.0, 400.0, 80.0, 60.0, 160, 120)  # 23 degrees across
    depth = np.full((120, 160), 3.0, np.float32)
    for min_overlap, expected in ((0.7, True), (0.0, False)):
        sel = selector(min_overlap=min_overlap)
        sel.is_keyframe(pose(), depth=depth, camera=narrow)
        assert sel.is_keyframe(pose(yaw_deg=10.0), camera=narrow) is expected
    assert KeyframeView.of(depth, narrow).overlap(pose(yaw_deg=10.0), narrow) == pytest.approx(0.56, abs=0.07)


def test_without_depth_the_scene_depth_comes_later_from_multi_view_stereo() -> None:
    sequence = walk(10.0, frames=60)
    sel = selector()
    chosen = flags(sel, sequence[:20], with_depth=False)
    # no depth known: no distance in pose units decides (0.2 units made every 4th frame a keyframe here, every
    # frame at ten times the scale): only turns and the every-N floor, the same in any unit
    assert chosen == [True] + [False] * 19
    for scale in (0.1, 1000.0):
        assert flags(selector(), walk(scale, frames=20), with_depth=False) == chosen
    sel.set_scene_depth(10.0)  # e.g. the multi-view depth of a recent keyframe
    assert sum(flags(sel, sequence[20:], with_depth=False)) <= 5
    for bad in (None, float("nan"), -1.0, 0.0):
        sel.set_scene_depth(bad)
        assert sel.scene_depth == 10.0


def test_the_view_and_scene_depth_survive_a_snapshot() -> None:
    sequence = walk(3.0, frames=80)
    sel = selector()
    first = flags(sel, sequence[:30])
    restored = selector()
    restored.load_state_dict(sel.state_dict())
    assert restored.scene_depth == pytest.approx(sel.scene_depth)
    assert flags(restored, sequence[30:]) == flags(sel, sequence[30:])
    assert sum(first) >= 2


def scaled(frame: Frame, scale: float) -> Frame:
    pose = frame.pose.copy()
    pose[:3, 3] *= scale
    return Frame(frame.index, frame.timestamp, frame.image, intrinsics=frame.intrinsics, depth=frame.depth * scale,
                 pose=pose)


@pytest.mark.parametrize("pose_mode", ["fixed", "seeded"])
def test_engine_keyframes_do_not_depend_on_the_unit_of_poses_and_depth(pose_mode: str) -> None:
    """Posed RGB-D on real frames (ICL, every third frame): poses and depth in metres or in decimetres choose the
    same keyframes, fewer than the every-N floor would."""
    frames = list(open_source(ICL_MINI, max_frames=40, resize=(80, 60), use_gt_poses=True))
    chosen = []
    for scale in (1.0, 10.0):
        config = SlamConfig.preset("test", threaded=False, mapping={"enabled": False}, loop={"enabled": False},
                                   input={"pose_mode": pose_mode, "surfel_init": "depth"},
                                   frontend={"keyframe_every": 1000})
        system = SlamSystem(config)
        chosen.append([system.push(scaled(f, scale)).is_keyframe for f in frames])
        system.close()
    assert chosen[0] == chosen[1]
    assert 4 <= sum(chosen[0]) <= 20


def drive(scale: float, frames: int = 12) -> list[tuple[np.ndarray, np.ndarray]]:
    """A car driving 0.8 m a frame toward a scene 12 m ahead (in units of `scale` metres)."""
    return [(pose(z=0.8 * k * scale), np.full((CAMERA.height, CAMERA.width), (12.0 - 0.8 * k) * scale, np.float32))
            for k in range(frames)]


def test_driving_forward_makes_a_keyframe_once_the_view_is_seen_closer() -> None:
    chosen = flags(selector(approach=0.1), drive(1.0))
    assert chosen == flags(selector(approach=0.1), drive(0.05))  # the same in the units of visual odometry
    assert chosen[:6] == [True, False, True, False, True, False]  # 1.6 m on 12 m: the view seen 13 % closer
    # parallax and overlap alone wait longer along the view (the rule before): the test can fail
    assert flags(selector(), drive(1.0))[:6] == [True, False, False, True, False, True]
    view = KeyframeView.plane(12.0, CAMERA)
    assert view.approach(pose(z=1.2)) == pytest.approx(0.1)
    assert abs(view.approach(pose(x=1.2))) < 1e-9  # sideways: no closer
    assert view.approach(pose(z=-1.2)) < 0
