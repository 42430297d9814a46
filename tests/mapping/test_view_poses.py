"""Keyframe cameras refined with the map (worker.mapping.view_poses): a camera stored off its true pose is moved
back toward it by the photometric refinement, cameras stored right stay put, and the final refinement hands the
motions to the engine."""

import math

import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, view, voxelized_surfels

from worker.config import MappingConfig
from worker.geometry import make_sim3, so3_exp
from worker.mapping.gaussian_map import corrected_pose, rigid_viewmat
from worker.mapping.refine import RefineView, refine_surfels
from worker.mapping.view_poses import ViewPoseCorrections
from worker.pipeline.mapping_stage import MappingStage

TRUE_POSES = [camera_pose(0.0), camera_pose(0.12), camera_pose(0.24, 0.05), camera_pose(0.1, 0.12)]


def _nudged(pose: torch.Tensor) -> torch.Tensor:
    """`pose` moved 2 cm sideways and 1 cm up, turned 0.6 degrees: about a pixel and a half at 60 px focal, 2 m."""
    nudge = make_sim3(so3_exp(torch.tensor([0.0, math.radians(0.6), 0.0], dtype=torch.float64)),
                      torch.tensor([0.02, -0.01, 0.0], dtype=torch.float64))
    return pose.to(torch.float64) @ nudge


def _map_of_true_views() -> torch.Tensor:
    return [voxelized_surfels(p, k).transform(p.float()) for k, p in enumerate(TRUE_POSES[:3])]


def _pixel_error(pose: torch.Tensor, truth: torch.Tensor) -> float:
    """Mean distance (pixels) between where the two cameras see the plane points the true camera sees: on a plane, a
    sideways shift and a turn look nearly alike, so the images, not the parameters, are compared."""
    points = view(truth)["world"].reshape(-1, 3).double()
    K = intrinsics().double()

    def pixels(c2w: torch.Tensor) -> torch.Tensor:
        camera = (points - c2w[:3, 3]) @ c2w[:3, :3].double()
        uv = camera @ K.T
        return uv[:, :2] / uv[:, 2:]

    return float((pixels(pose.double()) - pixels(truth.double())).norm(dim=-1).mean())


def test_a_corrections_identity_is_the_view_itself():
    cameras = ViewPoseCorrections(2)
    viewmat, _ = rigid_viewmat(camera_pose(0.1, 0.2, 0.3))
    assert torch.allclose(cameras.viewmat(1, viewmat.float()), viewmat.float())
    assert torch.equal(corrected_pose(camera_pose(0.1), torch.eye(4, dtype=torch.float64)), camera_pose(0.1))


def test_corrected_pose_keeps_the_scale_and_matches_the_corrected_viewmat():
    pose = camera_pose(0.3, -0.1, 0.2, scale=2.5)
    correction = make_sim3(so3_exp(torch.tensor([0.01, -0.02, 0.03], dtype=torch.float64)),
                           torch.tensor([0.05, 0.0, -0.02], dtype=torch.float64))
    moved = corrected_pose(pose, correction)
    viewmat, scale = rigid_viewmat(moved)
    assert abs(scale - 2.5) < 1e-9
    assert torch.allclose(viewmat, correction @ rigid_viewmat(pose)[0], atol=1e-12)


def test_a_camera_stored_off_its_pose_is_brought_back_and_the_others_stay():
    surfels = _map_of_true_views()
    from worker.mapping import Surfels

    world = Surfels.concat(surfels)
    stored = [*TRUE_POSES[:3], _nudged(TRUE_POSES[3])]
    views = []
    for truth, pose in zip(TRUE_POSES, stored):
        seen = view(truth)  # the photo is taken where the camera truly was
        views.append(RefineView(rigid_viewmat(pose)[0].float(), intrinsics(), seen["image"], seen["depth"]))
    before = _pixel_error(stored[3], TRUE_POSES[3])
    _, report = refine_surfels(world, torch.ones(len(world), dtype=torch.bool), views, iterations=400,
                               scene_scale=2.0, trainable_cameras=[False, True, True, True])
    assert len(report.view_corrections) == 4
    after = [_pixel_error(corrected_pose(p, c), t) for p, c, t in zip(stored, report.view_corrections, TRUE_POSES)]
    assert before > 1.0 and after[3] < 0.3 * before, (before, after)
    assert after[0] == 0.0 and max(after[1:3]) < 0.2, after


def test_without_train_poses_there_are_no_corrections():
    world = _map_of_true_views()[0]
    seen = view(TRUE_POSES[0])
    views = [RefineView(rigid_viewmat(TRUE_POSES[0])[0].float(), intrinsics(), seen["image"], seen["depth"])]
    _, report = refine_surfels(world, torch.ones(len(world), dtype=torch.bool), views, iterations=3)
    assert report.view_corrections == []


def test_the_final_refinement_returns_the_keyframes_motions():
    """Through the mapping stage: the nudged keyframe's returned world motion takes its stored pose toward its true
    one, the map's keyframe pose is the moved one, and without train_poses nothing moves."""
    results = {}
    for train in (False, True):
        stage = MappingStage(MappingConfig(refine_keyframes=4, refine_iterations=1, voxel_cap=0), threaded=False,
                             max_backlog=4)
        for kf, truth in enumerate(TRUE_POSES):
            pose = _nudged(truth) if kf == 3 else truth
            stage.map.add_keyframe(kf, pose, intrinsics(), view(truth)["image"], voxelized_surfels(truth, kf),
                                   view(truth)["depth"])
        results[train] = (stage.refine_all(passes=40, budget_s=math.inf, train_poses=train),
                          stage.map.keyframe_pose(3))
    assert results[False][0] == {}
    motions, map_pose = results[True]
    assert 3 in motions
    moved = torch.as_tensor(motions[3]) @ _nudged(TRUE_POSES[3])
    assert torch.allclose(moved, map_pose, atol=1e-9)
    assert _pixel_error(moved, TRUE_POSES[3]) < 0.7 * _pixel_error(_nudged(TRUE_POSES[3]), TRUE_POSES[3])
    assert WIDTH == 64 and HEIGHT == 48  # the scene the tolerances were set for
