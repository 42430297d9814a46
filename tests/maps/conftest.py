"""Real frames for the stored-map tests: the bundled ICL excerpt (the map's scene) and a TUM excerpt (another)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from worker.data.frame import Frame
from worker.data.sources import open_source
from worker.maps.localizer import MapView

DATA = Path(__file__).parents[1] / "data"


@pytest.fixture(scope="session")
def icl_frames() -> list[Frame]:
    return list(open_source(DATA / "icl_mini", use_gt_depth=True))


@pytest.fixture(scope="session")
def other_scene_frames() -> list[Frame]:
    return list(open_source(DATA / "tum_fr1_rpy_mini", use_gt_depth=True))


def camera_matrix(frame: Frame) -> np.ndarray:
    return np.asarray(frame.intrinsics.matrix(), np.float64)


def gray(frame: Frame) -> np.ndarray:
    return cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)


def views_of(frames: list[Frame]) -> list[MapView]:
    """A stored map's keyframes made from frames with their ground-truth poses and sensor depth."""
    return [MapView(f.index, f.gt_pose, camera_matrix(f), gray(f), f.depth) for f in frames]
