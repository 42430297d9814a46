"""The loop closer's keyframe points: held as float16 depth and the camera (a third of the points' memory),
unprojected on demand, re-projected when the camera is re-estimated, and kept across a snapshot."""

import torch

from protocol.codec import pack, unpack
from worker.geometry import unproject_depth
from worker.pipeline.loop_closer import DepthKeyframePoints


def test_points_come_from_the_depth_and_follow_a_new_camera():
    gen = torch.Generator().manual_seed(0)
    depth = 0.5 + 3.0 * torch.rand(24, 32, generator=gen)
    depth[0, :5] = 0.0
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    store = DepthKeyframePoints()
    store.add(7, depth, K)
    points, conf = store.keyframe_points(7)
    want = unproject_depth(depth, K)
    assert torch.allclose(points, want, rtol=1e-3, atol=1e-3)
    assert torch.equal(conf, (want[..., 2] > 0).float() + 1.0)
    assert store.depths[7].dtype == torch.float16 and store.depths[7].shape == depth.shape
    restored = DepthKeyframePoints()
    restored.load_state_dict(unpack(pack(store.state_dict())))
    assert torch.equal(restored.keyframe_points(7)[0], points) and len(restored) == 1
    K2 = torch.tensor([[45.0, 0, 16], [0, 45.0, 12], [0, 0, 1]])
    store.reproject(K2)
    assert torch.allclose(store.keyframe_points(7)[0], unproject_depth(depth, K2), rtol=1e-3, atol=1e-3)
