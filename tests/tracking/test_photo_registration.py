"""Photo registration (worker.tracking.photos) on real photos: every other frame of tests/data/icl_mini (frames 6
originals apart, a 3.7 m walk through a living room) registered one at a time, photos beyond a gap placed once a
later photo bridges it, mutual matching against OpenCV's brute-force matcher, and a msgpack snapshot that continues
as the original."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol.codec import pack, unpack
from worker.data import open_source
from worker.eval import absolute_trajectory_error
from worker.tracking.photos import IncrementalRegistration, PhotoRegistration, PhotoRegistrationConfig, extract_features
from worker.tracking.photos.matching import mutual_matches
from worker.tracking.projection import camera_matrix

DATA = Path(__file__).parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def photos():
    frames = list(open_source(str(DATA), use_gt_depth=False))
    features = {f.index: extract_features(cv2.cvtColor(f.image, cv2.COLOR_RGB2GRAY), 2000) for f in frames}
    return frames, features


def _register(photos, order: list[int]) -> tuple[IncrementalRegistration, dict[int, np.ndarray], list]:
    frames, features = photos
    registration = IncrementalRegistration(camera_matrix(frames[0].intrinsics))
    poses, outcomes = {}, []
    for i in order:
        done = registration.add(i, features[i])
        outcomes.append((i, done))
        if done.pose is not None:
            poses[i] = done.pose
        poses.update(done.posed)
    return registration, poses, outcomes


def _ate(photos, poses: dict[int, np.ndarray]) -> float:
    frames = photos[0]
    order = sorted(poses)
    return absolute_trajectory_error(np.stack([poses[i] for i in order]),
                                     np.stack([frames[i].gt_pose for i in order]), "sim3").rmse


def test_mutual_matches_are_opencvs_cross_checked_ratio_matches(photos) -> None:
    _, features = photos
    a, b = features[0], features[2]
    ia, ib = mutual_matches(a, b, 0.8)
    matcher = cv2.BFMatcher(cv2.NORM_L2)

    def passing(x, y):
        return {(m.queryIdx, m.trainIdx) for m, n in matcher.knnMatch(x.descriptors, y.descriptors, k=2)
                if m.distance < 0.8 * n.distance}

    expected = passing(a, b) & {(i, j) for j, i in passing(b, a)}
    assert len(expected) > 50
    assert set(zip(ia.tolist(), ib.tolist())) == expected


def test_photos_of_a_real_room_are_registered_on_its_path(photos) -> None:
    order = list(range(0, 71, 2))
    _, poses, outcomes = _register(photos, order)
    assert sorted(poses) == order  # every photo, the ones that waited for the first map included
    assert outcomes[0][1].state == "waiting" and any(done.state == "initialized" for _, done in outcomes)
    assert all(np.all(np.isfinite(p)) for p in poses.values())
    assert _ate(photos, poses) < 0.03  # metres, Sim(3), on a 3.7 m path (measured 1.4 cm)


def test_photos_beyond_a_gap_are_registered_when_a_later_photo_bridges_it(photos) -> None:
    beyond = list(range(50, 61, 2))  # the far end of the room, out of sight of photos 0-20
    order = list(range(0, 21, 2)) + beyond + list(range(22, 49, 2))
    _, poses, outcomes = _register(photos, order)
    states = dict((i, done.state) for i, done in outcomes)
    assert all(states[i] == "unregistered" for i in beyond)
    bridged = [(i, done) for i, done in outcomes if set(beyond) & set(done.posed)]
    assert bridged and bridged[0][0] > 20  # placed by a photo walking towards them
    assert sorted(poses) == sorted(order)
    assert _ate(photos, poses) < 0.03


def test_a_restored_registration_continues_as_the_original(photos) -> None:
    frames, _ = photos
    straight = PhotoRegistration()
    expected = [straight.track(f, f.intrinsics).pose for f in frames[0:40:2]]
    first = PhotoRegistration()
    for f in frames[0:20:2]:
        first.track(f, f.intrinsics)
    restored = PhotoRegistration()
    restored.load_state_dict(unpack(pack(first.state_dict())))
    got = [restored.track(f, f.intrinsics).pose for f in frames[20:40:2]]
    for a, b in zip(got, expected[10:]):
        np.testing.assert_allclose(a, b, atol=1e-3)  # descriptors travel in half precision


def test_the_source_reports_a_photo_it_cannot_register_as_lost_and_never_a_nan(photos) -> None:
    frames, _ = photos
    source = PhotoRegistration(PhotoRegistrationConfig())
    results = [source.track(f, f.intrinsics) for f in frames[0:12:2]]
    black = type(frames[0])(index=99, timestamp=50.0, image=np.zeros_like(frames[0].image))
    lost = source.track(black, frames[0].intrinsics)
    assert all(r.tracked for r in results) and results[-1].keyframe_hint
    assert not lost.tracked and lost.keyframe_hint is False and np.all(np.isfinite(lost.pose))
    np.testing.assert_allclose(lost.pose, results[-1].pose)
    assert [e.TYPE for e in lost.events] == ["tracking_lost"]
    with pytest.raises(ValueError, match="intrinsics"):
        PhotoRegistration().track(frames[0], None)
