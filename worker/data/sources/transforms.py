"""Photo captures with a `transforms.json` (instant-ngp / nerfstudio layout, poses from COLMAP).

The file gives one pinhole camera (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, or `camera_angle_x`), optional OpenCV
radial-tangential distortion (`k1`, `k2`, `k3`, `p1`, `p2`; with `camera_model` OPENCV_FISHEYE, the fisheye's
`k1`-`k4`) and per frame a `file_path` and a camera-to-world
`transform_matrix` in the OpenGL convention (x right, y up, z backwards). Frames are read in file-name order (the
capture order of a video or a photo series); their poses become ground truth in the OpenCV convention. Images are
undistorted on load, so the pinhole camera holds exactly; that camera is zoomed in just enough that every pixel
saw the scene (OpenCV's optimal new camera matrix with alpha 0): with the photo's own K, the pixels undistortion
brings in from outside the photo are black (fox: 1.7 % of the image, the outer 1-2 pixels at 270x480).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from protocol.lens import FISHEYE, MODEL_KEYS, RADTAN, distortion_problem
from worker.data.frame import Frame
from worker.geometry import Intrinsics
from worker.geometry.lens import Lens, undistorted_camera, undistortion

from .base import DatasetError, FrameRecord, RecordedSource, SourceOptions, finish_frame, natural_key, read_rgb

logger = logging.getLogger(__name__)

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips the camera's y and z axes


def _camera(data: dict, path: Path) -> tuple[Intrinsics, Lens | None]:
    try:
        width, height = int(data["w"]), int(data["h"])
        fx = float(data["fl_x"]) if "fl_x" in data else 0.5 * width / math.tan(0.5 * float(data["camera_angle_x"]))
        fy = float(data.get("fl_y", fx))
        cx, cy = float(data.get("cx", width / 2)), float(data.get("cy", height / 2))
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: needs w, h and fl_x (or camera_angle_x): {exc}") from exc
    model = FISHEYE if data.get("camera_model") == "OPENCV_FISHEYE" else RADTAN
    distortion = {"model": model, **{k: float(data[k]) for k in MODEL_KEYS[model] if k in data}}
    problem = distortion_problem(distortion, fx, fy, cx, cy, width, height)
    if problem:
        raise DatasetError(f"{path}: {problem}")
    return Intrinsics(fx, fy, cx, cy, width, height), Lens.from_wire(distortion)


def _pose(frame: dict, path: Path) -> np.ndarray:
    try:
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: a frame without a valid transform_matrix: {exc}") from exc
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise DatasetError(f"{path}: transform_matrix of {frame.get('file_path')} must be a finite 4x4")
    return matrix @ OPENGL_TO_OPENCV


class TransformsJsonSource(RecordedSource):
    """The frames of `root/transforms.json` whose image files exist (missing ones are skipped with a warning)."""

    def __init__(self, root: str | Path, options: SourceOptions, fps: float = 2.0) -> None:
        root = Path(root)
        path = root / "transforms.json"
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise DatasetError(f"cannot read {path}: {exc}") from exc
        if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
            raise DatasetError(f"{path}: expected an object with a 'frames' list")
        intrinsics, lens = _camera(data, path)
        self._undistortion = None
        if lens is not None:
            pinhole = undistorted_camera(intrinsics, lens)
            self._undistortion = undistortion(intrinsics, lens, pinhole)
            intrinsics = pinhole
        present = []
        for frame in data["frames"]:
            image_path = root / str(frame.get("file_path", ""))
            if image_path.is_file():
                present.append((image_path, _pose(frame, path)))
        skipped = len(data["frames"]) - len(present)
        if skipped:
            logger.warning("%s: %d of %d frames have no image file and are skipped", path, skipped,
                           len(data["frames"]))
        present.sort(key=lambda item: natural_key(item[0]))
        records = [FrameRecord(i / fps, image_path, gt_pose=pose) for i, (image_path, pose) in enumerate(present)]
        super().__init__(root.name, records, intrinsics, None, options,
                         image_size=(intrinsics.width, intrinsics.height))

    def _load(self, index: int, record: FrameRecord) -> Frame:
        image = read_rgb(record.image_path)
        if (image.shape[1], image.shape[0]) != self._native_size:
            raise DatasetError(f"{record.image_path} is {image.shape[1]}x{image.shape[0]}, the camera says "
                               f"{self._native_size[0]}x{self._native_size[1]}")
        if self._undistortion is not None:
            image = self._undistortion.image(image)
        return finish_frame(index, record.timestamp, image, self._native_intrinsics, None, record.gt_pose,
                            self.options)

