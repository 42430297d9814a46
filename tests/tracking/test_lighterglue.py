"""LighterGlue (`worker.tracking.xfeat.glue`, vendored weights) on real ICL frames (tests/data/icl_mini): its matches
follow a known warp; a frame 37 degrees and 1.1 m from a remembered keyframe, which XFeat's mutual nearest
neighbours cannot place, is placed by `LearnedPlaces.glue_relocalise` within centimetres of the ground truth; a place
whose map points disagree with the two-view motion of the matches is refused."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from worker.data import open_source
from worker.data.frame import Frame
from worker.tracking.features import OrbExtractor
from worker.tracking.learned_places import LearnedPlaces
from worker.tracking.relocalization import Place
from worker.tracking.vo_config import VisualOdometryConfig
from worker.tracking.xfeat import XFeatExtractor
from worker.tracking.xfeat.glue import LighterGlue

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"
PLACE, FRAME = 7, 57  # frames 21 and 171 of the sequence: 37 degrees and 1.10 m apart


@pytest.fixture(scope="module")
def mini() -> list[Frame]:
    return list(open_source(DATA, use_gt_depth=True, use_gt_poses=False))


def _gray(frame: Frame) -> np.ndarray:
    return cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)


def _K(frame: Frame) -> np.ndarray:
    i = frame.intrinsics
    return np.array([[i.fx, 0.0, i.cx], [0.0, i.fy, i.cy], [0.0, 0.0, 1.0]])


def _place(frame: Frame, orb: OrbExtractor) -> Place:
    """A remembered keyframe as visual odometry keeps one: its ORB keypoints on map points (here from the frame's
    depth and ground-truth pose) and its image."""
    gray = _gray(frame)
    found = orb.extract(gray)
    col = np.clip(found.keypoints[:, 0].astype(int), 0, gray.shape[1] - 1)
    row = np.clip(found.keypoints[:, 1].astype(int), 0, gray.shape[0] - 1)
    z = frame.depth[row, col].astype(np.float64)
    ok = z > 0
    uv, z = found.keypoints[ok].astype(np.float64), z[ok]
    K = _K(frame)
    camera = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], axis=1)
    world = camera @ frame.gt_pose[:3, :3].T + frame.gt_pose[:3, 3]
    return Place(frame.index, frame.gt_pose.copy(), uv.astype(np.float32), found.descriptors[ok], world, gray=gray)


def _error(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Position error (m) and rotation error (degrees) of a camera-to-world pose."""
    d = np.linalg.inv(truth) @ pose
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))))


def test_matches_follow_a_known_warp(mini):
    gray = _gray(mini[0])
    H = np.array([[0.9, 0.15, 20.0], [-0.12, 0.95, 10.0], [2e-4, 1e-4, 1.0]])  # a turn, zoom and tilt
    warped = cv2.warpPerspective(gray, H, (gray.shape[1], gray.shape[0]), flags=cv2.INTER_LINEAR)
    xfeat = XFeatExtractor(top_k=1024)
    a, b = xfeat.extract(gray), xfeat.extract(warped)
    ia, ib, scores = LighterGlue().match(a, gray.shape[::-1], b, warped.shape[::-1])
    assert len(ia) >= 150 and len(ia) == len(ib) == len(scores) and np.all(scores >= 0.1)
    expected = cv2.perspectiveTransform((a.keypoints[ia] - 0.5)[None].astype(np.float64), H)[0] + 0.5
    assert np.mean(np.linalg.norm(expected - b.keypoints[ib], axis=1) < 3.0) > 0.85
    empty = xfeat.extract(np.zeros((64, 64), np.uint8))
    assert len(LighterGlue().match(empty, (64, 64), b, warped.shape[::-1])[0]) == 0


def test_a_wide_baseline_is_placed_by_the_glue_where_mutual_neighbours_fail(mini):
    orb = OrbExtractor(VisualOdometryConfig())
    place, frame = _place(mini[PLACE], orb), mini[FRAME]
    gray, K = _gray(frame), _K(frame)
    learned = LearnedPlaces(1024, 0.82, 5.991, 30)
    current = learned.of_frame(FRAME, gray, orb.extract(gray).keypoints)  # as visual odometry does while lost
    assert learned.relocalise(current, [place], K, 50) is None
    found = learned.glue_relocalise(gray, [place], K, 50)
    assert found is not None
    hit, uv = found
    assert hit.place == PLACE and len(hit.keypoints) >= 12 and uv.shape[1] == 2
    position, rotation = _error(hit.pose, frame.gt_pose)
    assert position < 0.06 and rotation < 2.5  # the camera is 1.1 m from the place; mutual NN at 20 inliers: 27 cm
    assert learned.glue_pairs == 1

    # The same place with its map turned by 10 degrees about the camera: PnP finds a pose, the matches' two-view
    # motion disagrees with it.
    turn = cv2.Rodrigues(np.array([0.0, np.radians(10.0), 0.0]))[0]
    centre = place.pose[:3, 3]
    turned = Place(place.index, place.pose, place.keypoints, place.descriptors,
                   (place.points - centre) @ turn.T + centre, gray=place.gray)
    assert learned.glue_relocalise(gray, [turned], K, 50) is None
