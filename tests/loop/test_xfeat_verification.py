"""XFeat in loop verification (`worker.loop.pnp` with `worker.loop.xfeat_matcher`) on real ICL frames
(tests/data/icl_mini, depth as keyframe points): revisits from a 16-30 degree view change 0.4-0.7 m away, which
ORB's matches cannot verify, are verified by XFeat with the true relative pose; a pair that shares no view stays
rejected, and a keyframe's XFeat verifications are bounded."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from worker.geometry import relative_transform, sim3_decompose, so3_log
from worker.loop.oracle import load_rgbd_folder
from worker.loop.pnp import PnPRelocalizer
from worker.loop.xfeat_matcher import XFeatKeyframeMatcher
from worker.pipeline.loop_closer import DepthKeyframePoints


@pytest.fixture(scope="module")
def frames(request):
    return load_rgbd_folder(Path(request.config.rootpath) / "tests" / "data" / "icl_mini")


def _relocalizer(frames, keys: list[int], xfeat: bool, per_keyframe: int = 1) -> PnPRelocalizer:
    points = DepthKeyframePoints()
    for k in keys:
        points.add(k, frames[k].depth, frames[k].intrinsics.matrix())
    pnp = PnPRelocalizer(points, min_inliers=12, xfeat=XFeatKeyframeMatcher() if xfeat else None,
                         xfeat_min_inliers=50, xfeat_per_keyframe=per_keyframe)
    for k in keys:
        pnp.add_keyframe(k, frames[k].image)
    return pnp


@pytest.mark.parametrize("i,j", [(30, 42), (4, 32)])
def test_a_wide_revisit_orb_rejects_is_verified_by_xfeat(frames, i, j):
    truth = relative_transform(frames[i].pose, frames[j].pose)  # metric: both keyframes' points are depth
    turn = float(so3_log(truth[:3, :3]).norm())
    assert turn > 0.25 and float(truth[:3, 3].norm()) > 0.4  # a wide revisit: 16-30 degrees, 0.4-0.7 m

    orb = _relocalizer(frames, [i, j], xfeat=False).relocalize(i, j, frames[j].image, frames[j].intrinsics)
    assert not orb.accepted and orb.source == "pnp"

    pnp = _relocalizer(frames, [i, j], xfeat=True)
    c = pnp.relocalize(i, j, frames[j].image, frames[j].intrinsics)
    assert c.accepted and c.source == "pnp_xfeat", c.reason
    assert c.extra["inliers"] >= 50 and c.extra["orb"] == orb.reason
    s, R, t = sim3_decompose(torch.from_numpy(c.relative))
    assert float(s) == pytest.approx(1.0, abs=0.05)
    assert float(so3_log(truth[:3, :3].T @ R).norm()) < 0.035  # 2 degrees
    assert float((t - truth[:3, 3]).norm()) < 0.1 * float(truth[:3, 3].norm())
    assert pnp.xfeat_accepted == 1 and pnp.xfeat.passes == 2


def test_a_pair_sharing_no_view_stays_rejected_and_xfeat_tries_are_bounded(frames):
    pnp = _relocalizer(frames, [6, 30, 62], xfeat=True)
    c = pnp.relocalize(6, 62, frames[62].image, frames[62].intrinsics)  # opposite walls of the room
    assert not c.accepted and "XFeat" in c.reason
    # The keyframe's one XFeat verification is spent: the next candidate is ORB's alone, no network pass.
    passes = pnp.xfeat.passes
    c = pnp.relocalize(30, 62, frames[62].image, frames[62].intrinsics)
    assert "XFeat" not in c.reason and pnp.xfeat.passes == passes


def test_keyframe_images_are_kept_small_and_matched_in_their_own_pixels(frames):
    """A 640x480 keyframe is kept downscaled and JPEG-encoded (a long session keeps one per keyframe); its
    matches come back in its own pixels: twice those of the same view kept at 320x240."""
    image = frames[30].image  # [1, 3, 240, 320]
    large = torch.nn.functional.interpolate(image, scale_factor=2.0, mode="bilinear", align_corners=False)
    matcher = XFeatKeyframeMatcher()
    matcher.add_keyframe(0, large)
    matcher.add_keyframe(1, image)
    assert len(matcher.images[0][0]) < 40_000  # raw grey 640x480: 307 kB
    uv_large, uv_small = matcher.match(0, 1)
    assert len(uv_large) > 200
    off = np.linalg.norm(np.asarray(uv_large) - 2.0 * np.asarray(uv_small), axis=1)
    assert np.median(off) < 1.0 and np.mean(off <= 3.0) > 0.85  # a 1-pixel keypoint grid, doubled; a few wrong
    restored = XFeatKeyframeMatcher()
    restored.load_state_dict(matcher.state_dict())
    assert restored.images == matcher.images
