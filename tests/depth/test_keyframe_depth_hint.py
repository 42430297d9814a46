"""Keyframes whose pose source gives no depth (posed RGB) sweep the depth range of the newest keyframe multi-view
stereo has estimated, read when their depth is built: a keyframe queued before the previous one was built still
gets it (on KITTI the first dozen keyframes of posed RGB were queued together and swept a range that missed the
road)."""

from __future__ import annotations

import numpy as np
from scenes import Scene, pinhole, translation

from worker.depth import MultiViewDepthConfig
from worker.pipeline.depth_sources import MultiViewDepth, StereoBuilder

W, H = 160, 120
K = pinhole(W, H)
STEP = 0.3  # sideways per frame; the default range (4 to 100 median baselines) would start beyond the plane at 2
PLANE = 2.0


def _queue_two_keyframes() -> tuple[StereoBuilder, list]:
    scene = Scene(plane_depth=PLANE)
    builder = StereoBuilder(MultiViewDepthConfig())
    depth = MultiViewDepth(None, buffer_frames=16, frames_after=2, builder=builder)
    poses = {i: translation(STEP * i) for i in range(9)}
    sparse = None
    for i, pose in poses.items():
        image, gt = scene.render(pose, K, W, H)
        depth.add_frame(i, image)
        if i == 2:  # the first keyframe has a depth hint (a pose source's points), the second none
            sparse = np.where(np.arange(W)[None, :] % 8 == 0, gt, 0.0).astype(np.float32)
            depth.add_keyframe_at(i, K, sparse)
        elif i == 4:
            depth.add_keyframe_at(i, K, None)
    jobs = depth.ready_jobs(lambda i: poses[i], force=True)  # both queued before either is built
    return builder, jobs


def test_a_keyframe_queued_before_the_previous_was_built_sweeps_its_range() -> None:
    depth, jobs = _queue_two_keyframes()
    assert [job.kf_id for job in jobs] == [2, 4]
    assert depth.recent_hint == (None, None)
    _, _, first = depth.build(jobs[0])  # the mapping stage builds in keyframe order
    assert depth.recent_hint[1] is not None and abs(depth.recent_hint[1] - PLANE) < 0.05
    _, _, second = depth.build(jobs[1])
    second = second.numpy()
    confident = second > 0
    assert confident.mean() > 0.7, f"coverage {confident.mean():.2f}"
    assert np.median(np.abs(second[confident] - PLANE)) / PLANE < 0.01
    assert (first.numpy() > 0).mean() > 0.7
