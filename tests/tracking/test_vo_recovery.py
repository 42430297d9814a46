"""Visual odometry finding its way back on real ICL frames (tests/data/icl_mini, every third frame of ICL-NUIM
living room 1): a gap the optical flow cannot bridge restarts the map from the last tracked frame (two views, the
old map's scale), and a wider one is found again by XFeat matching against that frame's map points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.config import SlamConfig
from worker.data import open_source
from worker.data.frame import Frame
from worker.eval import absolute_trajectory_error
from worker.slam import SlamSystem
from worker.tracking.base import TrackingResult
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig

DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(DATA, use_gt_depth=False, use_gt_poses=False))


def _run_with_gaps(frames: list[Frame], step: int, config: VisualOdometryConfig | None = None
                   ) -> tuple[list[TrackingResult], list[Frame]]:
    """The first 20 frames, then every `step`-th (renumbered, so the gaps look like fast motion)."""
    sequence = frames[:20] + frames[20::step]
    vo = VisualOdometry(config)
    results = [vo.track(Frame(n, n / 10.0, f.image, f.intrinsics), f.intrinsics) for n, f in enumerate(sequence)]
    return results, sequence


def _ate_of_tracked(results: list[TrackingResult], sequence: list[Frame]) -> tuple[float, float]:
    poses = np.stack([r.pose for r in results])
    for event in (e for r in results for e in r.events if e.TYPE == "initialized"):
        for index, pose in event.frames:
            poses[index] = np.asarray(pose)
    tracked = [n for n, r in enumerate(results) if r.tracked]
    gt = np.stack([sequence[n].gt_pose for n in tracked])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    return absolute_trajectory_error(poses[tracked], gt, "sim3").rmse, path


def _methods(results: list[TrackingResult]) -> list[tuple[int, str]]:
    return [(n, e.method or "") for n, r in enumerate(results) for e in r.events if e.TYPE == "relocalized"]


def test_a_gap_the_flow_cannot_bridge_restarts_the_map_at_the_old_scale(frames):
    results, sequence = _run_with_gaps(frames, 6)
    restarts = [n for n, method in _methods(results) if method == "reinitialized"]
    lost = [n for n, r in enumerate(results) if any(e.TYPE == "tracking_lost" for e in r.events)]
    assert lost and restarts and restarts[0] >= lost[0]
    event = next(e for e in results[restarts[0]].events if getattr(e, "method", None) == "reinitialized")
    assert event.scale_from == "shared points" and event.shared_points >= 10
    assert all(r.tracked for r in results)  # the restart frame itself is tracked on the new map
    ate, path = _ate_of_tracked(results, sequence)
    assert ate < 0.02 * path  # one Sim(3) fits both maps: same world, same scale


def test_a_wide_gap_is_found_again_by_learned_matching(frames):
    results, sequence = _run_with_gaps(frames, 16)
    learned = [n for n, method in _methods(results) if method == "learned"]
    assert learned
    ate, path = _ate_of_tracked(results, sequence)
    assert ate < 0.02 * path
    without, _ = _run_with_gaps(frames, 16, VisualOdometryConfig(learned_relocalisation=False))
    assert not without[learned[0]].tracked  # optical flow, the restart and ORB places do not find that frame


def test_a_snapshot_taken_while_lost_continues_identically(frames):
    config = VisualOdometryConfig(learned_relocalisation=False)
    sequence = frames[:20] + frames[20::16]
    head, tail = sequence[:22], sequence[22:]
    vo = VisualOdometry(config)
    for n, f in enumerate(head):
        vo.track(Frame(n, n / 10.0, f.image, f.intrinsics), f.intrinsics)
    assert vo.status == "lost" and vo.anchor is not None
    restored = VisualOdometry()
    restored.load_state_dict(unpack(pack(vo.state_dict())))
    for n, f in enumerate(tail, start=len(head)):
        frame = Frame(n, n / 10.0, f.image, f.intrinsics)
        a, b = vo.track(frame, f.intrinsics), restored.track(frame, f.intrinsics)
        assert a.tracked == b.tracked and np.allclose(a.pose, b.pose)


def test_a_view_no_matcher_finds_begins_a_new_map_that_tracks(frames):
    """The camera reappears far from anything the old map saw (learned matching off): after two lost frames a new
    map initialises there (a `new_map` event, submap 1), placed at the last pose, and tracks the rest accurately
    in its own frame; the frames while it waits are not tracked and hold the last pose."""
    sequence = frames[:20] + frames[40:]
    vo = VisualOdometry(VisualOdometryConfig(learned_relocalisation=False, new_map_after_lost=2))
    results = [vo.track(Frame(n, n / 10.0, f.image, f.intrinsics), f.intrinsics) for n, f in enumerate(sequence)]
    assert [e.TYPE for e in results[20].events] == ["tracking_lost"]
    begun = [n for n, r in enumerate(results) if any(e.TYPE == "new_map" for e in r.events)]
    assert begun == [22]
    event = next(e for e in results[22].events if e.TYPE == "new_map")
    assert event.map == 2 and event.lost_frames == 2 and event.scene_depth > 0
    made = next(n for n, r in enumerate(results) if n > 22 and any(e.TYPE == "initialized" for e in r.events))
    assert all(not r.tracked and np.array_equal(r.pose, results[19].pose) for r in results[20:made])
    assert all(r.tracked and r.submap_id == 1 and r.quality > 0 for r in results[made:])
    assert all(r.submap_id == 0 for r in results[:20])
    new = list(range(made, len(sequence)))
    gt = np.stack([sequence[n].gt_pose for n in new])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    assert absolute_trajectory_error(np.stack([results[n].pose for n in new]), gt, "sim3").rmse < 0.02 * path
    # the new map starts where the old one was lost (no jump in the reported trajectory)
    assert np.linalg.norm(results[made].pose[:3, 3] - results[19].pose[:3, 3]) < 0.5
    # The frames it waited for (reported lost) are posed by its initialisation, in its frame and as accurately.
    initialized = next(e for e in results[made].events if e.TYPE == "initialized")
    assert initialized.map == 2
    waited = {int(i): np.asarray(p) for i, p in initialized.frames}
    assert set(waited) and set(waited) <= set(range(20, made)) and len(waited) >= made - 24
    posed = sorted(waited) + new
    poses = np.stack([waited[n] if n in waited else results[n].pose for n in posed])
    truth = np.stack([sequence[n].gt_pose for n in posed])
    assert absolute_trajectory_error(poses, truth, "sim3").rmse < 0.02 * path


def test_without_new_maps_a_far_view_stays_lost(frames):
    sequence = frames[:20] + frames[40:]
    vo = VisualOdometry(VisualOdometryConfig(learned_relocalisation=False, new_map_after_lost=0))
    results = [vo.track(Frame(n, n / 10.0, f.image, f.intrinsics), f.intrinsics) for n, f in enumerate(sequence)]
    assert not any(r.tracked for r in results[20:])


def test_the_engine_registers_the_frames_a_new_map_waited_for(frames):
    """Through the engine (mapping off): the new map's `initialized` event names the lost frames it posed
    (`registered_frames`), and the trajectory now holds their poses, not the held one."""
    sequence = frames[:20] + frames[40:]
    config = SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False},
                               tracking={"visual": {"learned_relocalisation": False, "new_map_after_lost": 2}})
    system = SlamSystem(config)
    results = [system.push(Frame(n, n / 10.0, f.image, f.intrinsics)) for n, f in enumerate(sequence)]
    system.finish()
    assert system.mode == "visual_odometry"
    named = [e for r in results for e in r.events if e.TYPE == "initialized" and e.registered_frames]
    assert len(named) == 1 and named[0].frames_revised == len(named[0].registered_frames)
    registered = named[0].registered_frames
    assert all(not results[i].tracked for i in registered)  # reported lost live ...
    poses = {i: p for i, _, p in system.trajectory("all")}
    held = poses[19]
    moved = [np.linalg.norm(poses[i][:3, 3] - held[:3, 3]) > 1e-6 for i in registered]
    assert sum(moved) >= len(registered) - 1  # ... posed now (the new map's first view is placed at the held pose)
    assert system.stats()["frames_registered_later"] == len(registered)
    later = [n for n in range(20, len(sequence)) if results[n].tracked or n in registered]
    gt = np.stack([sequence[n].gt_pose for n in later])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    assert absolute_trajectory_error(np.stack([poses[n] for n in later]), gt, "sim3").rmse < 0.02 * path
