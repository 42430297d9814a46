"""XFeat against remembered keyframes (`worker.tracking.learned_places`) on real ICL frames (tests/data/icl_mini):
a jump back to the view of an older keyframe, which optical flow and ORB place recognition miss, is relocalised
against that keyframe; a map restarted after such a jump is joined to the old map by XFeat where ORB finds no place.
Each sequence is the first 40 frames, then a jump back to frames seen early on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.data.frame import Frame
from worker.tracking.map_join import moved_pose
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def mini() -> list[Frame]:
    return list(open_source(DATA, use_gt_depth=False, use_gt_poses=False))


def _jump(mini: list[Frame], back: int) -> list[Frame]:
    """Frames 0-39, then frames back, back + 1, back + 2 again (renumbered as 40-42)."""
    order = [*range(40), back, back + 1, back + 2]
    return [Frame(n, n / 10.0, mini[k].image, mini[k].intrinsics) for n, k in enumerate(order)]


def _run(vo: VisualOdometry, frames: list[Frame]) -> list:
    return [vo.track(frame, frame.intrinsics) for frame in frames]


def test_a_jump_back_is_relocalised_by_xfeat_against_an_older_keyframe(mini):
    frames = _jump(mini, 5)
    # No restart from the last tracked frame: only a remembered keyframe can bring the jump back.
    config = VisualOdometryConfig(reinit_after_loss=False)
    vo = VisualOdometry(config)
    results = _run(vo, frames[:40])
    assert vo.learned.passes == 0  # smooth tracking never runs the network
    results += _run(vo, frames[40:41])
    jump = results[40]
    events = {e.TYPE: e for e in jump.events}
    assert "tracking_lost" in events  # the flow broke at the jump ...
    back = events["relocalized"]
    assert back.method == "learned keyframe" and back.place <= 8  # ... a keyframe of the first views, not 39
    assert back.inliers >= config.reloc_min_inliers and jump.tracked
    # The frame is frame 5's image: the relocalised pose is the pose frame 5 was tracked at.
    depth = vo.map_depth
    np.testing.assert_allclose(jump.pose[:3, :3], results[5].pose[:3, :3], atol=0.02)
    assert np.linalg.norm(jump.pose[:3, 3] - results[5].pose[:3, 3]) < 0.03 * depth
    # Tracking goes on from there, and a snapshot keeps the keyframe images XFeat needs.
    assert all(r.tracked for r in _run(vo, frames[41:]))
    restored = VisualOdometry()
    restored.load_state_dict(unpack(pack(vo.state_dict())))
    assert restored.keyframe_images.keys() == vo.keyframe_images.keys()
    assert sum(p.gray is not None for p in restored.retired) == sum(p.gray is not None for p in vo.retired) > 0

    # Without XFeat the same jump is not found again (ORB place recognition misses it).
    plain = VisualOdometry(config.model_copy(update={"learned_relocalisation": False}))
    assert not _run(plain, frames[:41])[40].tracked


def test_a_restarted_map_is_joined_by_xfeat_where_orb_finds_no_place(mini):
    frames = _jump(mini, 2)
    # ORB descriptor matching off (no two ORB descriptors are within 1 bit): a join can only come from XFeat.
    vo = VisualOdometry(VisualOdometryConfig(max_hamming=1))
    results = _run(vo, frames)
    events = [(n, e) for n, r in enumerate(results) for e in r.events]
    restart = next(n for n, e in events if getattr(e, "method", None) == "reinitialized")
    merged = [(n, e) for n, e in events if e.TYPE == "maps_merged"]
    assert restart == 40 and len(merged) == 1
    at, event = merged[0]
    assert event.method == "learned" and event.since == restart and event.place <= 8
    assert event.pairs >= 10 and 0.8 < event.scale < 1.25
    assert vo.join is None and vo.map_id == 0
    # The joined frame shows frame 2 + (at - 40)'s image: in the old map's frame it lies where that frame was.
    joined = moved_pose(np.asarray(event.correction), results[at].pose)
    seen = results[2 + at - 40].pose
    assert np.linalg.norm(joined[:3, 3] - seen[:3, 3]) < 0.05 * vo.map_depth
