"""XFeat in loop verification (`worker.loop.pnp` with `worker.loop.xfeat_matcher`) on real ICL frames
(tests/data/icl_mini, depth as keyframe points): revisits from a 16-30 degree view change 0.4-0.7 m away, which
ORB's matches cannot verify, are verified by XFeat with the true relative pose; a pair that shares no view stays
rejected, and a keyframe's XFeat verifications are bounded."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from worker.engine.loop_closer import DepthKeyframePoints
from worker.geometry import relative_transform, sim3_decompose, so3_log
from worker.loop.oracle import load_rgbd_folder
from worker.loop.pnp import PnPRelocalizer
from worker.loop.xfeat_matcher import XFeatKeyframeMatcher


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
