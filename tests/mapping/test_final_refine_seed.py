"""The final refinement's view order comes from `mapping.final_refine_seed`: one seed repeats, another differs."""

import math

import torch
from mapping_scene import camera_pose, intrinsics, view, voxelized_surfels

from worker.config import MappingConfig
from worker.engine.mapping_stage import MappingStage

POSES = [camera_pose(0.0), camera_pose(0.12), camera_pose(0.24, 0.05), camera_pose(0.1, 0.12)]


def _refined_colours(seed: int) -> torch.Tensor:
    stage = MappingStage(MappingConfig(refine_keyframes=4, refine_iterations=1, voxel_cap=0), threaded=False,
                         max_backlog=4)
    for kf, pose in enumerate(POSES):
        stage.map.add_keyframe(kf, pose, intrinsics(), view(pose)["image"], voxelized_surfels(pose, kf),
                               view(pose)["depth"])
    stage.refine_all(passes=1, budget_s=math.inf, seed=seed)
    return stage.map.surfels.colors.clone()


def test_the_seed_fixes_the_final_refinement():
    first, again, other = _refined_colours(0), _refined_colours(0), _refined_colours(5)
    assert torch.equal(first, again)
    assert not torch.allclose(first, other, atol=1e-6)
