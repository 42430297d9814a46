"""The live engine shape: tracking publishes poses while the mapping stage is stalled, mapping sheds work and says
so, finish() drains every stage, and a snapshot taken while mapping lags restores a system that continues exactly."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from live_sessions import live_config, push_all_within

from protocol.codec import unpack
from worker.data import Frame, open_source
from worker.pipeline.tracking_stage import follow_corrections
from worker.slam import SlamSystem

SIZE = (80, 60)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(Path(__file__).parents[1] / "data" / "icl_mini", max_frames=14, resize=SIZE,
                            use_gt_depth=True))


def test_tracking_publishes_poses_while_mapping_is_stalled_and_finish_drains(frames) -> None:
    system = SlamSystem(live_config(mapping={"shed_backlog": 0}, queue_size=64))
    with system.mapping_stage.lock:  # the mapping stage cannot map anything while this is held
        results = push_all_within(system, frames)
        assert len(results) == len(frames)
        assert all(np.all(np.isfinite(r.pose)) for r in results)
        keyframes = sum(r.is_keyframe for r in results)
        stats = system.live_stats()
        assert keyframes >= 4 and stats["mapping_lag_keyframes"] >= keyframes - 1
        assert system.mapping_stage.keyframes_mapped == 0
    system.finish()
    assert system.mapping_stage.pending == 0 and system.loop_stage.pending == 0
    last_frame = system.last_frame_mapped is not None  # finish() maps the newest view too
    assert system.mapping_stage.keyframes_mapped == keyframes + last_frame
    assert system.live_stats()["mapping_lag_keyframes"] == 0
    assert system.num_gaussians > 0


def test_mapping_sheds_work_when_it_falls_behind_and_reports_it(frames) -> None:
    system = SlamSystem(live_config(mapping={"shed_backlog": 1, "merge_only_backlog": 2}, queue_size=3))
    with system.mapping_stage.lock:
        results = push_all_within(system, frames)
    system.finish()
    keyframes = sum(r.is_keyframe for r in results)
    shed = system.stats()["keyframes_shed"]
    assert shed["dropped"] > 0 and shed["merge_only"] > 0  # the backlog was 6 when the stage woke up
    assert system.mapping_stage.keyframes_mapped + shed["dropped"] == keyframes + (system.last_frame_mapped is not None)
    assert len(system.mapping_stage.map.keyframe_ids) == system.mapping_stage.keyframes_mapped


def test_mapping_keeps_every_refinement_when_it_keeps_up(frames) -> None:
    system = SlamSystem(live_config())
    for frame in frames:  # inline-like pace: the stage is idle before each keyframe
        system.push(frame)
        system.mapping_stage.wait_idle()
    system.finish()
    assert system.stats()["keyframes_shed"] == {"reduced": 0, "merge_only": 0, "dropped": 0}


def test_snapshot_while_mapping_lags_restores_and_continues_exactly(frames) -> None:
    cut = 8
    system = SlamSystem(live_config(mapping={"shed_backlog": 0}, queue_size=64))
    with system.mapping_stage.lock:
        push_all_within(system, frames[:cut])
        future = system.begin_snapshot()  # returns at once: the map part comes when the map lock is free
        assert not future.done()
        later = push_all_within(system, frames[cut:])  # tracking goes on meanwhile
    blob = future.result(timeout=120)
    system.finish()
    restored = SlamSystem.restore(blob)
    assert [i for i, _, _ in restored.trajectory()] == [f.index for f in frames[:cut]]
    keyframes_before_cut = len(restored.trajectory("keyframes"))
    restored.mapping_stage.wait_idle()  # the jobs the snapshot held as queued are mapped again
    assert restored.mapping_stage.keyframes_mapped == keyframes_before_cut  # everything submitted before the cut
    again = [restored.push(f) for f in frames[cut:]]
    for a, b in zip(later, again):
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-3)  # the snapshot keeps depth as float16
        assert a.is_keyframe == b.is_keyframe
    restored.finish()
    assert restored.mapping_stage.keyframes_mapped == system.mapping_stage.keyframes_mapped


def test_a_snapshot_does_not_wait_for_the_mapping_backlog(frames) -> None:
    # Slow keyframes (many refinement iterations) and a backlog: the map part is taken between two keyframes, the
    # keyframes still queued go into the snapshot as data and the restored system maps them.
    system = SlamSystem(live_config(mapping={"shed_backlog": 0, "refine_iterations": 400}, queue_size=64))
    with system.mapping_stage.lock:
        push_all_within(system, frames[:12])
        future = system.begin_snapshot()
    blob = future.result(timeout=600)
    backlog = system.mapping_stage.pending
    queued = unpack(unpack(blob)["map"])["queued"]
    assert len(queued) >= 2 and backlog >= 1, (len(queued), backlog)
    system.close()
    restored = SlamSystem.restore(blob)
    restored.mapping_stage.wait_idle()
    keyframes = len(restored.trajectory("keyframes"))
    assert restored.mapping_stage.keyframes_mapped == keyframes == len(restored.mapping_stage.map.keyframe_ids)
    restored.close()


def test_a_snapshot_does_not_wait_for_the_loop_closing_backlog(frames) -> None:
    # Loop closing stalled: its keyframe nodes and loop queries wait in its queue; the snapshot takes its state now,
    # with them as data, and the restored stage works through them.
    system = SlamSystem(live_config())
    system.push(frames[0])  # the session's loop-closing stage exists from its first frame
    with system.loop_stage.lock:
        push_all_within(system, frames[1:])
        future = system.begin_snapshot()
        time.sleep(0.2)
        assert not future.done()  # the loop part needs the stage's lock
    blob = future.result(timeout=300)
    queued = unpack(unpack(blob)["loop"])["queued"]
    kinds = {item["kind"] for item in queued}
    assert {"keyframe", "query"} <= kinds, kinds
    system.close()
    restored = SlamSystem.restore(blob)
    restored.loop_stage.wait_idle()
    keyframes = [i for i, _, _ in restored.trajectory("keyframes")]
    assert sorted(restored.pose_graph.nodes) == keyframes
    restored.close()


def test_keyframes_made_after_an_optimisation_follow_the_newest_corrected_one() -> None:
    def at(x: float) -> np.ndarray:
        pose = np.eye(4)
        pose[0, 3] = x
        return pose

    current = {0: at(0.0), 2: at(1.0), 4: at(2.0), 6: at(3.0)}
    corrected = {0: at(0.0), 2: at(1.5)}  # the loop stage optimised keyframes 0 and 2 only
    moved = follow_corrections(current, corrected)
    np.testing.assert_allclose(moved[2], at(1.5))
    np.testing.assert_allclose(moved[4], at(2.5))  # rigidly with keyframe 2: no jump between 2 and 4
    np.testing.assert_allclose(moved[6], at(3.5))
    assert set(moved) == set(current)


def test_keyframes_that_follow_correction_after_correction_stay_similarities() -> None:
    """The loop stage lags tracking by a few keyframes and corrects after every keyframe (RGB-D's dense edges): the
    newest keyframes follow one correction, then are corrected themselves while newer ones follow. A pose built
    from a followed pose and the closed-form inverse of another must not keep their shear: it doubled with every
    correction and reached a reflection on TUM fr1/xyz after ~60."""
    rng = np.random.default_rng(0)

    def rigid(scale: float) -> np.ndarray:
        pose = np.eye(4)
        pose[:3, :3] = cv2.Rodrigues(rng.normal(scale=scale, size=3))[0]
        pose[:3, 3] = rng.normal(scale=scale, size=3)
        return pose

    def exact(pose: np.ndarray) -> np.ndarray:  # the graph's solution: a rigid pose near the one it was given
        u, _, vt = np.linalg.svd(pose[:3, :3])
        out = pose.copy()
        out[:3, :3] = u @ vt
        return rigid(0.002) @ out

    current = {0: rigid(1.0)}
    for keyframe in range(1, 100):
        current[keyframe] = current[keyframe - 1] @ rigid(0.05)  # tracking's newest keyframe
        known = sorted(current)[:-3]  # the loop stage is 3 keyframes behind, and corrects after each one
        if known:
            current = follow_corrections(current, {k: exact(current[k]) for k in known})
    for pose in current.values():
        rotation = pose[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
        assert np.linalg.det(rotation) > 0


def test_a_tracking_resolution_tracks_large_frames_small_and_maps_them_whole() -> None:
    """Frames twice the tracking resolution: the pose source sees them at half size (intrinsics scaled), the poses
    match tracking the frames at that size, and the map still receives the full frames."""
    source = Path(__file__).parents[1] / "data" / "icl_mini"
    large = list(open_source(source, max_frames=8, resize=(160, 120), use_gt_depth=True))
    small = list(open_source(source, max_frames=8, resize=(80, 60), use_gt_depth=True))
    seen: list[tuple[int, int, float]] = []
    system = SlamSystem(live_config(tracking={"max_side": 80}, threaded=False))
    reference = SlamSystem(live_config(threaded=False))
    for big, little in zip(large, small, strict=True):
        result = system.push(big)
        source_frame = system.tracking_stage._tracked_frame
        seen.append((source_frame.width, source_frame.height, source_frame.intrinsics.fx))
        expected = reference.push(little)
        assert np.allclose(result.pose[:3, 3], expected.pose[:3, 3], atol=0.02)
    assert {s[:2] for s in seen} == {(80, 60)}
    assert abs(seen[0][2] - large[0].intrinsics.fx / 2) < 1e-6
    system.finish()
    reference.finish()
    assert system.num_gaussians > 2 * reference.num_gaussians  # surfels from 4x the pixels


def _keyframe_psnr(system: SlamSystem, frames: list[Frame]) -> float:
    """Mean PSNR of the map rendered at its keyframes against their images."""
    by_index = {f.index: f for f in frames}
    values = []
    for index, _, pose in system.trajectory("keyframes"):
        frame = by_index[index]
        rgb, _ = system.render_view(pose, frame.intrinsics.matrix(), frame.width, frame.height)
        mse = np.mean((rgb.astype(np.float64) - frame.image.astype(np.float64)) ** 2)
        values.append(10 * np.log10(255.0**2 / max(mse, 1e-9)))
    return float(np.mean(values))


def _stalled_then_idle(frames: list[Frame], idle_refine: bool) -> SlamSystem:
    """Every keyframe waits behind a stalled mapping stage (so all but the newest are merged without refinement),
    then the stage is left alone until it owes nothing (or 120 s)."""
    config = live_config(mapping={"shed_backlog": 1, "merge_only_backlog": 1, "idle_refine": idle_refine,
                                  "archived_images": 64},
                         queue_size=64)
    system = SlamSystem(config)
    with system.mapping_stage.lock:
        push_all_within(system, frames)
    system.mapping_stage.wait_idle()
    deadline = time.monotonic() + 120
    while idle_refine and system.stats()["keyframes_owed"] and time.monotonic() < deadline:
        time.sleep(0.05)
    return system


def test_refinement_shed_while_mapping_lagged_is_caught_up_when_the_stage_is_idle(frames) -> None:
    """Keyframes merged without refinement under load are owed their refinement; the idle stage pays it back,
    oldest first, and the map then renders those keyframes better than a stage that keeps its debt."""
    caught_up = _stalled_then_idle(frames, idle_refine=True)
    in_debt = _stalled_then_idle(frames, idle_refine=False)
    stats, debt_stats = caught_up.stats(), in_debt.stats()
    assert stats["keyframes_shed"]["merge_only"] > 0 and stats["keyframes_owed"] == 0
    assert stats["keyframes_caught_up"] >= stats["keyframes_shed"]["merge_only"]
    assert debt_stats["keyframes_caught_up"] == 0 and debt_stats["keyframes_shed"]["merge_only"] > 0
    assert _keyframe_psnr(caught_up, frames) > _keyframe_psnr(in_debt, frames) + 0.5
    caught_up.close()
    in_debt.close()


def test_finish_counts_its_drain_against_the_final_refinement_budget(frames) -> None:
    """finish() is bounded as a whole: when draining the stages used up `final_refine_budget_s`, the final
    refinement does not run at all (its passes would otherwise take their own budget on top)."""
    config = live_config(mapping={"final_refine_passes": 50, "final_refine_budget_s": 1e-6}, threaded=False)
    system = SlamSystem(config)
    for frame in frames:
        system.push(frame)
    system.finish()
    assert system.timings.counts["map_final_refine"] == 1
    assert system.timings.seconds["map_final_refine"] < 0.5  # 50 passes would take seconds
    unbounded = SlamSystem(live_config(mapping={"final_refine_passes": 2, "final_refine_budget_s": 0},
                                       threaded=False))
    for frame in frames:
        unbounded.push(frame)
    unbounded.finish()
    assert unbounded.timings.seconds["map_final_refine"] > system.timings.seconds["map_final_refine"]
