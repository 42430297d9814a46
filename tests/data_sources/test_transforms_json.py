"""The instant-ngp / nerfstudio `transforms.json` reader: camera, OpenGL -> OpenCV poses, undistortion, order."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from dataset_writers import write_image

from worker.data.sources import DatasetError, TransformsJsonSource, detect_format, open_source


def _gl_pose(x: float, yaw_deg: float) -> list[list[float]]:
    """An OpenGL camera-to-world (looks down -z) turned by `yaw_deg` about y, at x."""
    a = np.radians(yaw_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    pose[0, 3] = x
    return pose.tolist()


def _capture(root, distortion: dict | None = None, missing: str | None = None) -> None:
    frames = []
    for i, name in enumerate(["frame_10.png", "frame_2.png", "frame_1.png"]):
        if name != missing:
            write_image(root / "images" / name, 40, 30, value=10 * i)
        frames.append({"file_path": f"images/{name}", "transform_matrix": _gl_pose(float(i), 10.0 * i)})
    data = {"fl_x": 50.0, "fl_y": 52.0, "cx": 20.0, "cy": 15.0, "w": 40, "h": 30, "frames": frames}
    data.update(distortion or {})
    (root / "transforms.json").write_text(json.dumps(data))


def test_camera_poses_in_opencv_convention_and_file_order(tmp_path):
    _capture(tmp_path)
    assert detect_format(tmp_path) == "transforms"
    source = open_source(tmp_path, use_gt_poses=True, resize=(20, 15))
    assert isinstance(source, TransformsJsonSource) and len(source) == 3
    assert source.intrinsics.fx == pytest.approx(25.0) and source.intrinsics.fy == pytest.approx(26.0)
    frames = list(source)
    # natural order: frame_1, frame_2, frame_10 (file_path order, not the json's)
    assert [f.gt_pose[0, 3] for f in frames] == [2.0, 1.0, 0.0]
    for frame in frames:
        assert frame.image.shape == (15, 20, 3)
        R = frame.pose[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        # OpenCV cameras look along +z: the OpenGL camera's viewing direction is its -z axis
        yaw = np.radians(10.0 * round(frame.gt_pose[0, 3]))
        assert np.allclose(R[:, 2], [-np.sin(yaw), 0.0, -np.cos(yaw)])
        assert np.allclose(R[:, 1], [0.0, -1.0, 0.0])


def test_distortion_is_removed_and_missing_images_are_skipped(tmp_path):
    _capture(tmp_path, {"k1": -0.3, "k2": 0.05}, missing="frame_2.png")
    source = open_source(tmp_path)
    assert len(source) == 2
    first = next(iter(source))
    raw = cv2.cvtColor(cv2.imread(str(tmp_path / "images" / "frame_1.png")), cv2.COLOR_BGR2RGB)
    K = np.array([[50.0, 0, 20.0], [0, 52.0, 15.0], [0, 0, 1]])
    distortion = np.array([-0.3, 0.05, 0.0, 0.0, 0.0])
    camera = source.intrinsics
    assert camera.fx != 50.0 and camera.fy != 52.0  # the camera whose pixels all lie inside the photo
    undistorted = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
    expected = cv2.undistort(raw, K, distortion, newCameraMatrix=undistorted)
    assert np.array_equal(first.image, expected) and not np.array_equal(first.image, raw)


def test_undistorted_photos_have_no_black_border(tmp_path):
    """Every pixel of an undistorted photo saw the scene: undistorting with the photo's own camera brings black
    in at the borders (pixels from outside the photo), which views then render and are scored against."""
    _capture(tmp_path, {"k1": 0.25})
    for name in ("frame_1.png", "frame_2.png", "frame_10.png"):
        cv2.imwrite(str(tmp_path / "images" / name), np.full((30, 40, 3), 200, np.uint8))
    image = next(iter(open_source(tmp_path))).image
    assert image.min() >= 190, np.argwhere(image.min(-1) < 190)[:5]
    K = np.array([[50.0, 0, 20.0], [0, 52.0, 15.0], [0, 0, 1]])
    assert cv2.undistort(image, K, np.array([0.25, 0.0, 0.0, 0.0, 0.0])).min() < 100  # what the old camera did


@pytest.mark.parametrize("content, message", [
    ("not json", "cannot read"),
    (json.dumps({"frames": "x"}), "'frames' list"),
    (json.dumps({"frames": [], "w": 4}), "fl_x"),
    (json.dumps({"fl_x": 5, "w": 4, "h": 3, "frames": [{"file_path": "a.png", "transform_matrix": [[1]]}]}),
     "4x4"),
])
def test_malformed_transforms_are_clear_errors(tmp_path, content, message):
    write_image(tmp_path / "a.png")
    (tmp_path / "transforms.json").write_text(content)
    with pytest.raises(DatasetError, match=message):
        open_source(tmp_path)
