"""XFeat's work per frame is bounded (`worker.tracking.learned_places`): a frame runs at most its budget of network
passes, its own pass is made once and shared, a remembered keyframe not described within the budget is described on
a later frame; a lost camera is still relocalised with the smallest budget. Real frames: tests/data/icl_mini."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from worker.data import open_source
from worker.data.frame import Frame
from worker.tracking.learned_places import LearnedPlaces
from worker.tracking.relocalization import Place
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig
from worker.tracking.xfeat import torch_threads

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def mini() -> list[Frame]:
    return list(open_source(DATA, use_gt_depth=False, use_gt_poses=False))


def _gray(frame: Frame) -> np.ndarray:
    return cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)


def _place(index: int, gray: np.ndarray) -> Place:
    keypoints = np.array([[40.5, 30.5], [160.5, 120.5], [250.5, 200.5]], np.float32)
    return Place(index, np.eye(4), keypoints, np.zeros((3, 32), np.uint8), np.ones((3, 3)), gray=gray)


def test_a_frame_runs_at_most_its_passes_and_the_rest_waits(mini):
    learned = LearnedPlaces(top_k=256, min_similarity=0.82, chi2_px=5.991, min_inliers=30, passes_per_frame=2)
    a, b = _place(3, _gray(mini[3])), _place(6, _gray(mini[6]))
    learned.begin_frame(10)
    frame = learned.of_frame(10, _gray(mini[10]))
    assert frame is not None and len(frame) > 50 and learned.passes == 1
    again = learned.of_frame(10, _gray(mini[10]), np.array([[100.5, 100.5]], np.float32))
    assert learned.passes == 1 and len(again) == len(frame) + 1  # the frame's pass is shared; corners described
    assert learned.of_place(a) is not None and learned.passes == 2
    assert learned.of_place(b) is None and learned.passes_left == 0  # the budget is spent: b waits
    assert learned.of_frame(11, _gray(mini[11])) is None
    learned.begin_frame(11)
    assert learned.of_place(b) is not None and learned.of_place(a) is not None  # a is cached: no pass
    assert learned.passes == 3 and learned.most_in_a_frame == 2


def test_torch_threads_apply_to_the_calling_thread_only():
    """A running thread (the mapping stage's) keeps its thread count while another runs XFeat on one."""
    before = torch.get_num_threads()
    asked, seen = threading.Event(), []

    def mapping_stage() -> None:
        torch.ones(4).sum()  # a thread that has run torch operators
        seen.append(torch.get_num_threads())
        asked.wait(timeout=10)
        seen.append(torch.get_num_threads())

    other = threading.Thread(target=mapping_stage)
    other.start()
    while not seen:
        threading.Event().wait(0.01)
    with torch_threads(1):
        assert torch.get_num_threads() == 1
        asked.set()
        other.join()
    assert seen[1] == seen[0]
    assert torch.get_num_threads() == before


def test_a_jump_back_is_relocalised_within_the_smallest_budget(mini):
    """Frames 0-39, then frames 5-16 again: with two passes a frame (its own and one keyframe's: the most alike in
    ORB words comes first) the jump is relocalised against a keyframe of the first views, and no frame ran more."""
    order = [*range(40), *range(5, 17)]
    frames = [Frame(n, n / 10.0, mini[k].image, mini[k].intrinsics) for n, k in enumerate(order)]
    config = VisualOdometryConfig(reinit_after_loss=False, learned_passes_per_frame=2, new_map_after_lost=0)
    vo = VisualOdometry(config)
    results = [vo.track(frame, frame.intrinsics) for frame in frames]
    back = next(e for r in results[40:] for e in r.events if e.TYPE == "relocalized")
    assert back.method == "learned keyframe" and back.place <= 16 and back.frame <= 43
    assert all(r.tracked for r in results[back.frame:])
    assert vo.learned.most_in_a_frame == 2
