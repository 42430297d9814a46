"""Posed RGB-D mode: the given poses and depth build the map without the model (the backend in isolation)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from worker.config import SlamConfig
from worker.data import Frame, open_source
from worker.eval import depth_l1, psnr
from worker.slam import SlamSystem

SIZE = (80, 60)


def rgbd_config(**overrides) -> SlamConfig:
    return SlamConfig.preset("test", input={"pose_mode": "fixed", "surfel_init": "depth"},
                             frontend={"keyframe_every": 3, "keyframe_parallax": 1.0},  # the schedule alone
                             **overrides)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_source(Path(__file__).parents[1] / "data" / "icl_mini", max_frames=7, resize=SIZE,
                            use_gt_poses=True))


@pytest.fixture(scope="module")
def mapped(frames: list[Frame]) -> tuple[SlamSystem, list]:
    system = SlamSystem(rgbd_config())
    results = [system.push(f) for f in frames]
    system.finish()
    return system, results


def test_given_poses_are_kept_and_keyframes_follow_the_schedule(frames, mapped) -> None:
    system, results = mapped
    assert system.mode == "posed"
    for frame, result in zip(frames, results):
        np.testing.assert_allclose(result.pose, frame.pose, atol=1e-9)
        assert result.revision == 0 and result.events == []
    assert [r.is_keyframe for r in results] == [True, False, False, True, False, False, True]
    assert [i for i, _, _ in system.trajectory("keyframes")] == [0, 3, 6]


def test_non_keyframe_renders_match_the_images_and_depth(frames, mapped) -> None:
    system, results = mapped
    K = frames[0].intrinsics.matrix().numpy()
    for frame, result in zip(frames, results):
        if result.is_keyframe:
            continue
        rgb, depth = system.render_view(frame.pose, K, *SIZE)
        assert rgb.dtype == np.uint8 and rgb.shape == (SIZE[1], SIZE[0], 3) and depth.dtype == np.float32
        assert psnr(rgb, frame.image) > 20.0
        assert depth_l1(depth, frame.depth, "none").value < 0.08
    # looking the other way sees (almost) nothing of the map: the scores above are not free
    away = frames[1].pose.copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    rgb, _ = system.render_view(away, K, *SIZE)
    assert psnr(rgb, frames[1].image) < 15.0


def test_ply_export_has_every_gaussian(mapped) -> None:
    from plyfile import PlyData

    system, _ = mapped
    ply = PlyData.read(io.BytesIO(system.export_ply()))
    assert len(ply["vertex"]) == system.num_gaussians > 500


def test_threaded_backend_gives_the_same_result(frames, mapped) -> None:
    inline, _ = mapped
    system = SlamSystem(rgbd_config(threaded=True, mapping={"shed_backlog": 0}))
    for frame in frames:
        system.push(frame)
    system.finish()
    assert system.num_gaussians == inline.num_gaussians
    K = frames[0].intrinsics.matrix().numpy()
    a, _ = system.render_view(frames[2].pose, K, *SIZE)
    b, _ = inline.render_view(frames[2].pose, K, *SIZE)
    assert np.abs(a.astype(int) - b.astype(int)).mean() < 1.0


def test_bad_input_is_rejected(frames) -> None:
    system = SlamSystem(rgbd_config(mapping={"enabled": False}))
    with pytest.raises(ValueError, match="Frame"):
        system.push("not a frame")
    first = system.push(frames[0])
    without_pose = system.push(Frame(1, 0.1, frames[1].image, frames[1].intrinsics, frames[1].depth))
    assert not without_pose.tracked and [e.TYPE for e in without_pose.events] == ["tracking_lost"]
    np.testing.assert_allclose(without_pose.pose, first.pose)  # held: no error, the session goes on
    with pytest.raises(ValueError, match="80x60"):
        system.push(Frame(2, 0.2, np.zeros((30, 40, 3), np.uint8), pose=np.eye(4)))
    with pytest.raises(ValueError, match="not after"):
        system.push(frames[0])
    with pytest.raises(ValueError, match="mapping is disabled"):
        system.render_view(np.eye(4), np.eye(3), 8, 8)
    system.finish()
    with pytest.raises(ValueError, match="finished"):
        system.push(frames[1])


def test_render_view_checks_its_arguments(frames, mapped) -> None:
    system, _ = mapped
    K = frames[0].intrinsics.matrix().numpy()
    with pytest.raises(ValueError, match="4x4"):
        system.render_view(np.eye(3), K, *SIZE)
    with pytest.raises(ValueError, match="render size"):
        system.render_view(frames[0].pose, K, 0, 10)


def test_pruning_can_be_switched_off(frames) -> None:
    def surfels_per_keyframe(prune: bool) -> list[int]:
        system = SlamSystem(rgbd_config(mapping={"prune": prune, "refine_iterations": 0}))
        counts = [system.num_gaussians for f in frames if system.push(f).is_keyframe]
        system.finish()
        return counts

    kept, pruned = surfels_per_keyframe(False), surfels_per_keyframe(True)
    assert kept == sorted(kept) and kept[-1] > kept[0]  # nothing is ever removed
    assert kept[-1] > pruned[-1]  # where pruning removes some


def test_final_refinement_over_archived_keyframes_improves_the_map(frames) -> None:
    """With keyframe images archived, finish() refines the whole map against every keyframe (once, timed)."""
    K = frames[0].intrinsics.matrix().numpy()

    def run(archived: int, passes: int) -> tuple[SlamSystem, float]:
        system = SlamSystem(rgbd_config(mapping={"refine_keyframes": 1, "refine_iterations": 1,
                                                 "archived_images": archived, "final_refine_passes": passes}))
        results = [system.push(f) for f in frames]
        system.finish()
        scores = [psnr(system.render_view(f.pose, K, *SIZE)[0], f.image) for f, r in zip(frames, results)
                  if not r.is_keyframe]
        return system, float(np.mean(scores))

    window_only, window_psnr = run(archived=0, passes=4)
    refined, refined_psnr = run(archived=4, passes=4)
    assert refined.mapping_stage.map.held_images == 3 and window_only.mapping_stage.map.held_images == 1
    assert refined.timings.counts["map_final_refine"] == 1
    assert refined_psnr > window_psnr + 1.0, (window_psnr, refined_psnr)  # measured: 28.0 vs 24.8 dB
