"""A SLAM session in a stored map: it tracks in its own world, anchors once fixes agree, and then every pose
(earlier ones too) is in the map's world; another scene never anchors; a snapshot keeps the anchoring."""

from __future__ import annotations

import numpy as np

from worker.data.frame import Frame
from worker.maps.session_in_map import SessionInMap
from worker.slam import SlamConfig, SlamSystem

from .conftest import views_of


def _config() -> SlamConfig:
    # inline stages (the same run every time); no mapping: these tests are about poses
    return SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False})


def _session(frames: list[Frame], views: list) -> tuple[SlamSystem, SessionInMap]:
    in_map = SessionInMap("map1", 1, "localize", lambda: views, map_metric=True)
    return SlamSystem(_config(), intrinsics=frames[0].intrinsics, in_map=in_map), in_map


def _events(results, kind: str) -> list:
    return [e for r in results for e in r.events if e.TYPE == kind]


def test_a_session_in_a_map_publishes_its_poses_in_the_maps_world(icl_frames) -> None:
    frames = icl_frames[:40]
    system, in_map = _session(frames, views_of(icl_frames[::4]))
    results = [system.push(f) for f in frames]
    relocalized = _events(results, "relocalized")
    assert len(relocalized) == 1 and relocalized[0].map_id == "map1"
    first = next(r.index for r in results if any(e.TYPE == "relocalized" for e in r.events))
    assert first <= 5  # anchored within the first frames
    assert results[first].revision > results[0].revision  # the earlier poses were revised with it
    errors = [np.linalg.norm(pose[:3, 3] - frames[i].gt_pose[:3, 3]) for i, _, pose in system.trajectory()]
    assert np.sqrt(np.mean(np.square(errors))) < 0.04  # in the map's world: no alignment
    assert system.stats()["map_relocalizations"] == 1 and in_map.anchored
    system.finish()


def test_another_scene_stays_in_its_own_world(icl_frames, other_scene_frames) -> None:
    system, in_map = _session(other_scene_frames, views_of(icl_frames[::2]))
    results = [system.push(f) for f in other_scene_frames]
    assert not _events(results, "relocalized") and not in_map.anchored
    assert np.allclose(results[0].pose, np.eye(4))  # the session's own world starts at its first frame
    assert in_map.misses == len(other_scene_frames)


def test_a_restored_session_keeps_its_anchoring(icl_frames) -> None:
    frames = icl_frames[:24]
    views = views_of(icl_frames[::4])
    system, _ = _session(frames, views)
    for f in frames[:16]:
        system.push(f)
    restored_map = SessionInMap("map1", 1, "localize", lambda: views, map_metric=True)
    restored = SlamSystem.restore(system.snapshot(), in_map=restored_map)
    assert restored_map.anchored
    for f in frames[16:]:
        result = restored.push(f)
        assert np.linalg.norm(result.pose[:3, 3] - f.gt_pose[:3, 3]) < 0.06
    system.close()
    restored.close()
