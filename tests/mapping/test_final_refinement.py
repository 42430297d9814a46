"""The final refinement: its view order comes from `mapping.final_refine_seed` (one seed repeats, another differs);
its learning rates decay to `mapping.final_refine_lr_end`."""

import contextlib
import math

import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, psnr, view, voxelized_surfels

from worker.config import MappingConfig
from worker.pipeline.mapping_stage import MappingStage

POSES = [camera_pose(0.0), camera_pose(0.12), camera_pose(0.24, 0.05), camera_pose(0.1, 0.12)]


def _refined_render(seed: int, lr_end: float = 1.0) -> torch.Tensor:
    config = MappingConfig(refine_keyframes=4, refine_iterations=1, voxel_cap=0, final_refine_lr_end=lr_end)
    stage = MappingStage(config, threaded=False, max_backlog=4)
    for kf, pose in enumerate(POSES):
        stage.map.add_keyframe(kf, pose, intrinsics(), view(pose)["image"], voxelized_surfels(pose, kf),
                               view(pose)["depth"])
    stage.refine_all(passes=3, budget_s=math.inf, seed=seed)
    return stage.map.render(POSES[1], intrinsics(), WIDTH, HEIGHT).rgb


def test_the_seed_fixes_the_final_refinement():
    first, again, other = _refined_render(0), _refined_render(0), _refined_render(5)
    assert torch.equal(first, again)
    assert not torch.allclose(first, other, atol=1e-6)


def test_the_learning_rates_decay_to_the_configured_factor():
    truth = view(POSES[1])["image"]
    constant, decayed, again = _refined_render(0), _refined_render(0, lr_end=0.1), _refined_render(0, lr_end=0.1)
    assert torch.equal(decayed, again) and not torch.allclose(decayed, constant, atol=1e-4)
    assert psnr(decayed, truth) > 20 and psnr(constant, truth) > 20


def test_a_time_bound_final_refinement_decays_by_time():
    """With a deadline that will cut the refinement short, the factor follows the time spent: near the deadline it
    reaches the end factor whatever the iterations done."""
    import time

    from worker.mapping.gaussian_map import GaussianMap, MapConfig

    gmap = GaussianMap(MapConfig(final_refine_lr_end=0.01))
    began = time.perf_counter()
    by_iterations = gmap._final_lr_schedule(0, 100, began, None)
    assert abs(by_iterations(50) - 0.1) < 1e-9 and by_iterations(0) == 1.0
    by_time = gmap._final_lr_schedule(0, 100, began - 9.99, began + 0.01)  # 99.9 % of the time spent
    assert by_time(0) < 0.0105
    assert GaussianMap(MapConfig())._final_lr_schedule(0, 100, began, None) is None


def test_renders_and_exports_get_the_map_between_two_steps_of_the_final_refinement():
    """A client asking for the map while a session finishes: the final refinement (here bounded by 60 s only) lets
    a render and a PLY export in between two of its steps, instead of after its end. They see the map as the last
    finished chunk of the refinement left it, whole (as many surfels as the map has)."""
    import threading

    class Stop(Exception):
        pass

    config = MappingConfig(refine_keyframes=4, refine_iterations=1, voxel_cap=0)
    stage = MappingStage(config, threaded=False, max_backlog=4)
    for kf, pose in enumerate(POSES):
        stage.map.add_keyframe(kf, pose, intrinsics(), view(pose)["image"], voxelized_surfels(pose, kf),
                               view(pose)["depth"])
    steps, stop = [], threading.Event()
    let_readers_in = stage._let_readers_in

    def step_done() -> None:
        steps.append(1)
        if stop.is_set():
            raise Stop  # ends the refinement here, once the test has its answers
        let_readers_in()

    def refine() -> None:
        with contextlib.suppress(Stop):
            stage.refine_all(passes=2000, budget_s=60.0)

    stage._let_readers_in = step_done
    refinement = threading.Thread(target=refine)
    refinement.start()
    try:
        while not steps:  # the refinement holds the lock and runs its steps
            refinement.join(0.01)
        out = stage.render(POSES[1], intrinsics(), WIDTH, HEIGHT)
        ply = stage.to_ply_bytes()
        assert refinement.is_alive()  # answered while the refinement still runs
        assert out.rgb.shape == (HEIGHT, WIDTH, 3) and bool(torch.isfinite(out.rgb).all())
        assert f"element vertex {stage.num_gaussians()}".encode() in ply
    finally:
        stop.set()
        refinement.join(60)
    assert not refinement.is_alive()
