"""Pose validation at the gateway: similarities pass; non-finite, sheared, reflected, degenerate, absurd poses are
refused with `bad_pose` (frame messages) or 400 (render)."""

from __future__ import annotations

import cv2
import msgpack
import numpy as np
import pytest
from fastapi import HTTPException

from service.frame_validation import FrameRejected, check_frame_message
from service.pose_check import PoseLimits, pose_problem
from service.routes_results import render_params


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle)[0]


def pose(rot=np.eye(3), t=(0.0, 0.0, 0.0), scale: float = 1.0) -> list[float]:
    m = np.eye(4)
    m[:3, :3] = scale * np.asarray(rot)
    m[:3, 3] = t
    return m.reshape(-1).tolist()


def test_rigid_and_similar_poses_pass():
    rng = np.random.default_rng(0)
    for _ in range(50):
        rot = rotation(rng.normal(size=3), rng.uniform(0, np.pi))
        t = rng.normal(size=3) * 10
        assert pose_problem(pose(rot, t)) is None
        assert pose_problem(pose(rot, t, scale=float(rng.uniform(0.01, 100)))) is None
        # float32 round-off of a phone's pose stays within tolerance
        assert pose_problem(np.float32(pose(rot, t)).astype(float).tolist()) is None


@pytest.mark.parametrize("values, fragment", [
    (pose(t=(float("nan"), 0, 0)), "finite"),
    (pose(t=(float("inf"), 0, 0)), "finite"),
    ([0.0] * 16, "last row"),
    ([0.0] * 15 + [1.0], "determinant"),
    (pose(rot=np.diag([1.0, 1.0, -1.0])), "reflection"),
    (pose(rot=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "not rigid"),
    (pose(rot=np.diag([1.0, 2.0, 1.0])), "not rigid"),
    (pose(t=(1e300, 0, 0)), "translation"),
    (pose(t=(2e4, 0, 0)), "translation"),
    (pose(scale=1e-5), "scale"),
    (pose(scale=1e5), "scale"),
    (pose()[:12], "16 values"),
    (pose()[:15] + [2.0], "last row"),
])
def test_bad_poses_are_refused(values, fragment):
    problem = pose_problem(values)
    assert problem is not None and fragment in problem


def test_limits_are_configurable():
    assert pose_problem(pose(t=(50, 0, 0)), PoseLimits(max_translation=10)) is not None
    slightly_sheared = pose(rot=[[1, 1e-4, 0], [0, 1, 0], [0, 0, 1]])
    assert pose_problem(slightly_sheared) is None
    assert pose_problem(slightly_sheared, PoseLimits(tolerance=1e-6)) is not None


def frame(pose_values) -> bytes:
    jpeg = cv2.imencode(".jpg", np.zeros((24, 32, 3), np.uint8))[1].tobytes()
    return msgpack.packb({"type": "frame", "seq": 5, "timestamp": 0.0, "image": jpeg, "pose": pose_values})


def test_frame_messages_with_bad_poses_get_bad_pose():
    assert check_frame_message(frame(pose(scale=2.0, t=(1, 2, 3))), 1 << 20, None).seq == 5
    for values in ([0.0] * 16, pose(rot=[[1, 3, 0], [0, 1, 0], [0, 0, 1]]), pose(t=(1e300, 0, 0)), "not a list",
                   pose()[:4], [True] * 16):
        with pytest.raises(FrameRejected) as err:
            check_frame_message(frame(values), 1 << 20, None)
        assert err.value.code == "bad_pose" and err.value.seq == 5


def test_render_refuses_bad_poses_with_400():
    record = {"intrinsics": '{"fx": 50, "fy": 50, "cx": 16, "cy": 12, "width": 32, "height": 24}'}
    ok = render_params(record, ",".join(map(str, pose(scale=0.5))), None, None, None, None, None, None, "color",
                       1 << 20)
    assert ok["width"] == 32
    for values in ([0.0] * 16, pose(rot=np.diag([1.0, -1.0, 1.0]))):
        with pytest.raises(HTTPException) as err:
            render_params(record, ",".join(map(str, values)), None, None, None, None, None, None, "color", 1 << 20)
        assert err.value.status_code == 400 and "camera-to-world" in err.value.detail
