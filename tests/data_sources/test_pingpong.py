"""A recorded sequence played forward and back: indices and timestamps keep growing, frames come back in order."""

from pathlib import Path

import numpy as np
import pytest

from worker.data import DatasetError, open_source
from worker.data.sources.pingpong import sweep_order

ICL = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


def test_sweep_order_turns_without_repeating_the_turning_frame():
    assert sweep_order(4, 1) == [0, 1, 2, 3]
    assert sweep_order(4, 3) == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]
    with pytest.raises(DatasetError):
        sweep_order(4, 0)


def test_pingpong_plays_the_folder_forward_and_back_with_growing_indices():
    once = list(open_source(ICL, max_frames=5))
    source = open_source(ICL, max_frames=5, pingpong=3)
    frames = list(source)
    assert len(source) == len(frames) == 13
    assert [f.index for f in frames] == list(range(13))
    assert np.all(np.diff([f.timestamp for f in frames]) > 0)
    for frame, position in zip(frames, sweep_order(5, 3), strict=True):
        assert np.array_equal(frame.image, once[position].image)
        assert np.array_equal(frame.gt_pose, once[position].gt_pose)
        assert np.array_equal(frame.depth, once[position].depth)
    assert source.intrinsics == once[0].intrinsics


def test_pingpong_refuses_a_stream_it_cannot_replay():
    with pytest.raises(DatasetError, match="pingpong"):
        open_source("synthetic://seed=1?frames=4", pingpong=2)
