"""Keyframe points from given depth for PnP loop closure: depth-only storage, snapshots, older snapshots."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from protocol.codec import pack, unpack
from worker.geometry import unproject_depth
from worker.pipeline.loop_closer import DepthKeyframePoints


def test_points_come_back_exactly_from_a_snapshot_and_follow_a_new_camera(icl_frames):
    frame = icl_frames[3]
    depth = frame.depth.float()
    K = frame.intrinsics.matrix(torch.float32)
    store = DepthKeyframePoints()
    store.add(7, depth, K)
    points, conf = store.keyframe_points(7)
    np.testing.assert_allclose(points.numpy(), unproject_depth(depth, K).numpy(), rtol=1e-3, atol=1e-3)
    assert torch.equal(conf > 1.5, depth > 0)
    state = unpack(pack(store.state_dict()))
    assert state["depths"][0].dtype == np.float16 and state["depths"][0].nbytes == depth.numel() * 2
    restored = DepthKeyframePoints()
    restored.load_state_dict(state)
    assert torch.equal(restored.keyframe_points(7)[0], points)
    wider = K.clone()
    wider[0, 0] *= 1.1
    restored.reproject(wider)
    assert torch.allclose(restored.keyframe_points(7)[0][..., 0], points[..., 0] / 1.1, atol=1e-3)
    with pytest.raises(ValueError, match="not a keyframe"):
        restored.keyframe_points(8)


def test_snapshots_that_stored_points_still_restore(icl_frames):
    frame = icl_frames[5]
    K = frame.intrinsics.matrix(torch.float32)
    legacy = unproject_depth(frame.depth.float(), K).to(torch.float16)
    store = DepthKeyframePoints()
    store.load_state_dict({"keys": [4], "points": [legacy.numpy()]})
    np.testing.assert_allclose(store.cameras[4].numpy(), K.numpy(), rtol=1e-3, atol=0.05)
    np.testing.assert_allclose(store.keyframe_points(4)[0].numpy(), legacy.float().numpy(), atol=5e-3)
