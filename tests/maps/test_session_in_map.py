"""A SLAM session in a stored map: it tracks in its own world, anchors once fixes agree, and then every pose
(earlier ones too) is in the map's world; another scene never anchors; a snapshot keeps the anchoring."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.maps.session_in_map import SessionInMap
from worker.slam import SlamConfig, SlamSystem

from .conftest import views_of


def _config() -> SlamConfig:
    # inline stages (the same run every time); no mapping: these tests are about poses
    return SlamConfig.preset("rgbd", threaded=False, mapping={"enabled": False})


def _session(frames: list[Frame], views: list, config: SlamConfig | None = None
             ) -> tuple[SlamSystem, SessionInMap]:
    in_map = SessionInMap("map1", 1, "localize", lambda: views, map_metric=True)
    return SlamSystem(config or _config(), intrinsics=frames[0].intrinsics, in_map=in_map), in_map


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


def test_device_poses_still_being_judged_are_already_placed_in_the_map(icl_frames) -> None:
    """Posed RGB (`pose_mode` auto judges the device poses over the first frames): the session looks those frames
    up in the map while judging, so it is anchored before the verdict and the frames after the anchoring come out
    in the map's world, though the device's own world is elsewhere."""
    device_world = np.eye(4)
    device_world[:3, :3] = cv2.Rodrigues(np.array([0.1, -0.3, 0.2]))[0]
    device_world[:3, 3] = [0.7, -0.2, 1.5]
    frames = [replace(f, depth=None, pose=device_world @ f.gt_pose) for f in icl_frames[:30]]
    system, in_map = _session(frames, views_of(icl_frames[::4]), SlamConfig.preset(
        "rgbd", threaded=False, mapping={"enabled": False}, input={"pose_choice": {"within_frames": 20}}))
    results = [system.push(f) for f in frames]
    kinds = [[e.TYPE for e in r.events] for r in results]
    anchored = next(i for i, k in enumerate(kinds) if "relocalized" in k)
    verdict = next(i for i, k in enumerate(kinds) if "pose_source_chosen" in k)
    assert anchored <= 5 < verdict
    for r in results[anchored:verdict]:  # provisional poses, already in the map's world
        assert np.linalg.norm(r.pose[:3, 3] - frames[r.index].gt_pose[:3, 3]) < 0.03
    errors = [np.linalg.norm(pose[:3, 3] - frames[i].gt_pose[:3, 3]) for i, _, pose in system.trajectory()]
    assert np.sqrt(np.mean(np.square(errors))) < 0.03 and in_map.anchored
    system.finish()
