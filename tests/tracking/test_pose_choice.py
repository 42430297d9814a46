"""pose_mode auto with posed RGB frames (no depth): the first frames judge the device poses against the images
(worker.tracking.pose_agreement) on real ICL frames. Exact poses are kept as the odometry (`prior`); the same poses
with every position off by a fifth of a frame's step are judged to disagree, and visual odometry tracks from the
device's pose at the verdict on (`seeded`), said by a `pose_source_chosen` event, without a jump; an explicit
pose_mode is left alone; a snapshot continues the choice."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import open_source
from worker.slam import SlamSystem
from worker.tracking.pose_agreement import PoseAgreement

DATA = Path(__file__).parents[1] / "data" / "icl_mini"  # every third frame of ICL living room 1, 320x240
FRAMES = 34


@pytest.fixture(scope="module")
def frames():
    return list(open_source(str(DATA), max_frames=FRAMES, use_gt_depth=False, use_gt_poses=True))


@pytest.fixture(scope="module")
def noisy(frames) -> list[np.ndarray]:
    """The exact poses with each position moved at random by 20 % of the median step between frames (9 mm)."""
    positions = np.stack([f.pose[:3, 3] for f in frames])
    step = float(np.median(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
    rng = np.random.default_rng(0)
    poses = [np.array(f.pose, np.float64) for f in frames]
    for pose in poses:
        pose[:3, 3] += 0.2 * step * rng.standard_normal(3)
    return poses


def _judge(frames, poses) -> tuple[int, object]:
    agreement = PoseAgreement(step=2, triples=8, within_frames=30, max_ratio=1.5)
    K = frames[0].intrinsics.matrix().numpy()
    for k, (frame, pose) in enumerate(zip(frames, poses)):
        if agreement.add(frame.image, pose, K):
            return k, agreement.result
    raise AssertionError("no verdict within the frames")


def test_exact_poses_agree_with_the_images_and_noisy_positions_do_not(frames, noisy) -> None:
    at, exact = _judge(frames, [f.pose for f in frames])
    assert at <= 20 and exact.triples == 8
    assert exact.agree and exact.ratio < 1.2 and exact.given_px < 1.0, exact
    _, off = _judge(frames, noisy)
    assert not off.agree and off.ratio > 3.0, off
    assert off.fitted_px == pytest.approx(exact.fitted_px)  # the images' own fit does not depend on the poses


def _session(frames, poses, pose_mode: str = "auto"):
    config = SlamConfig.preset("default", threaded=False, mapping={"enabled": False},
                               input={"pose_mode": pose_mode})
    system = SlamSystem(config, intrinsics=frames[0].intrinsics)
    results = [system.push(replace(f, pose=p.copy())) for f, p in zip(frames, poses)]
    return system, results


def _chosen(results) -> list[tuple[int, dict]]:
    return [(r.index, e) for r in results for e in r.events if e.TYPE == "pose_source_chosen"]


def test_exact_poses_stay_the_odometry(frames) -> None:
    system, results = _session(frames, [f.pose for f in frames])
    [(at, event)] = _chosen(results)
    assert event.pose_source == "prior" and event.ratio <= event.max_ratio and at <= 20
    assert system.pose_source_choice()["pose_source"] == "prior"
    for result, frame in zip(results, frames):
        np.testing.assert_allclose(result.pose, frame.pose, atol=1e-9)
    # the judging's points, triangulated with the device poses, tell the keyframe selector the scene's depth before
    # any keyframe has its multi-view depth (ICL frame 0: median depth 1.85 m)
    assert 1.5 < system.pose_source.scene_depth < 2.2


def test_noisy_poses_hand_tracking_to_seeded_visual_odometry_without_a_jump(frames, noisy) -> None:
    system, results = _session(frames, noisy)
    [(at, event)] = _chosen(results)
    assert event.pose_source == "seeded" and event.ratio > event.max_ratio and at <= 20
    assert "disagree" in event.reason and f"{event.max_ratio:g}" in event.reason
    summary = system.pose_source_choice()
    assert summary["pose_source"] == "seeded" and summary["pose_agreement"]["judged"]
    # While judging, frames get the device's poses (provisional) and no keyframe; at the verdict the seeded
    # odometry goes through them again from the first frame's device pose, and the trajectory is revised.
    for result, pose in zip(results[:at], noisy):
        np.testing.assert_allclose(result.pose, pose, atol=1e-9)
        assert not result.is_keyframe and result.revision == 0
    assert event.frames_replayed == at + 1 and event.revision == results[at].revision > 0
    trajectory = system.trajectory("all")
    assert [index for index, _, _ in trajectory] == [f.index for f in frames]
    assert trajectory[0][0] in {index for index, _, _ in system.trajectory("keyframes")}
    np.testing.assert_allclose(trajectory[0][2], noisy[0], atol=1e-9)  # it starts where the session began
    true = np.stack([f.pose[:3, 3] for f in frames])
    ours = np.stack([pose[:3, 3] for _, _, pose in trajectory])
    step = np.median(np.linalg.norm(np.diff(true, axis=0), axis=1))
    assert np.linalg.norm(np.diff(ours, axis=0), axis=1).max() < 4 * step  # no jump, at the switch or after
    assert np.linalg.norm(results[at].pose[:3, 3] - results[at - 1].pose[:3, 3]) < 4 * step
    # once visual odometry is initialised, the motion from frame to frame is the images', not the noisy device's
    # (what multi-view stereo and the map need; the position drifts slowly instead, held by the device's priors):
    # the judged frames' too
    later = slice(6, None)
    true_steps = np.diff(true, axis=0)[later]
    ours_error = np.linalg.norm(np.diff(ours, axis=0)[later] - true_steps, axis=1).mean()
    device = np.stack([p[:3, 3] for p in noisy])
    device_error = np.linalg.norm(np.diff(device, axis=0)[later] - true_steps, axis=1).mean()
    assert ours_error < 0.5 * device_error, (ours_error, device_error)

    restored = SlamSystem.restore(system.snapshot())  # the choice and the seeded tracker go on
    assert restored.pose_source_choice()["pose_source"] == "seeded"
    more = restored.push(replace(frames[-1], index=frames[-1].index + 1, timestamp=frames[-1].timestamp + 0.1,
                                 pose=noisy[-1].copy()))
    assert not _chosen([more]) and np.linalg.norm(more.pose[:3, 3] - ours[-1]) < 4 * step


def test_an_explicit_pose_mode_is_not_judged(frames, noisy) -> None:
    system, results = _session(frames[:24], noisy[:24], pose_mode="prior")
    assert not _chosen(results) and system.pose_source_choice() == {"pose_source": "prior", "pose_agreement": None}
    for result, pose in zip(results, noisy):
        np.testing.assert_allclose(result.pose, pose, atol=1e-9)


def test_without_parallax_the_device_poses_are_kept(frames, noisy) -> None:
    still = [replace(frames[0], index=k, timestamp=k / 30) for k in range(31)]  # a camera that does not move
    system, results = _session(still, noisy[:31])
    [(at, event)] = _chosen(results)
    assert at == 29 and event.pose_source == "prior" and "parallax" in event.reason
    assert system.pose_source_choice()["pose_agreement"]["judged"]


def test_a_snapshot_from_before_the_choice_resumes_on_the_device_poses(frames) -> None:
    from worker.tracking.pose_choice import ChosenDevicePoses
    from worker.tracking.sources import DevicePoses

    old = DevicePoses()
    old.track(frames[0], frames[0].intrinsics)
    chosen = ChosenDevicePoses(new_seeded=lambda: None)
    chosen.load_state_dict(old.state_dict())  # what a worker without the choice snapshot
    assert chosen.summary()["pose_source"] == "prior" and not chosen.judging
    np.testing.assert_allclose(chosen.track(frames[1], frames[1].intrinsics).pose, frames[1].pose)


def test_too_few_triples_keep_the_device_poses_without_saying_they_disagree(frames, noisy) -> None:
    # The noisy poses disagree, but with fewer triples than asked for the verdict is no judgement: `agree` is None.
    config = SlamConfig.preset("default", threaded=False, mapping={"enabled": False},
                               input={"pose_mode": "auto", "pose_choice": {"min_triples": 50}})
    system = SlamSystem(config, intrinsics=frames[0].intrinsics)
    results = [system.push(replace(f, pose=p.copy())) for f, p in zip(frames, noisy)]
    [(_, event)] = _chosen(results)
    assert event.pose_source == "prior" and "too few" in event.reason
    assert event.triples < 50 and event.agree is None and event.ratio > event.max_ratio
    assert system.pose_source_choice()["pose_agreement"]["agree"] is None


def test_a_snapshot_while_judging_keeps_the_judged_frames_for_the_verdict(frames, noisy) -> None:
    config = SlamConfig.preset("default", threaded=False, mapping={"enabled": False}, input={"pose_mode": "auto"})
    system = SlamSystem(config, intrinsics=frames[0].intrinsics)
    first = [system.push(replace(f, pose=p.copy())) for f, p in zip(frames[:8], noisy[:8])]
    assert not _chosen(first) and system.needs_every_frame and system.trajectory("all") == []
    restored = SlamSystem.restore(system.snapshot())
    rest = [restored.push(replace(f, pose=p.copy())) for f, p in zip(frames[8:], noisy[8:])]
    [(at, event)] = _chosen(rest)  # (the triples measured before the snapshot count; their tracks start again)
    assert event.frames_replayed == at + 1 and event.pose_source == "seeded"
    assert [index for index, _, _ in restored.trajectory("all")] == [f.index for f in frames]
    np.testing.assert_allclose(restored.trajectory("all")[0][2], noisy[0], atol=1e-9)


def test_a_stream_that_ends_while_judging_is_decided_and_mapped_at_finish(frames, noisy) -> None:
    system, results = _session(frames[:10], noisy[:10])
    assert not _chosen(results) and system.trajectory("all") == []
    system.finish()
    [event] = [e for e in system.finish_events if e.TYPE == "pose_source_chosen"]
    assert event.frames_replayed == 10 and event.pose_source in ("prior", "seeded")
    assert [index for index, _, _ in system.trajectory("all")] == [f.index for f in frames[:10]]
    assert system.trajectory("keyframes")[0][0] == frames[0].index
