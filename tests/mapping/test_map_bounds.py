"""The map follows the scene, not the session: the voxel cap, the view-local merge and the bounded final refinement."""

import math
import time

import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, view, voxelized_surfels

from protocol.codec import pack, unpack
from worker.mapping.fusion import FusionThresholds
from worker.mapping.gaussian_map import GaussianMap, MapConfig
from worker.mapping.voxel_grid import capped_mask, voxel_keys


def capped_mask_oracle(present, offered, candidates, cap, finer):
    """The rule of `capped_mask`, voxel by voxel in plain Python."""
    keep = [False] * len(offered)
    used = {}
    for i, (key, candidate) in enumerate(zip(offered.tolist(), candidates.tolist(), strict=True)):
        if not candidate:
            continue
        n_offered, n_present = offered.tolist().count(key), present.tolist().count(key)
        room = min(n_offered, cap) - n_present if n_offered > finer * n_present else 0
        if used.get(key, 0) < room:
            keep[i] = True
            used[key] = used.get(key, 0) + 1
    return torch.tensor(keep)


def test_capped_mask_matches_the_voxel_by_voxel_rule():
    gen = torch.Generator().manual_seed(0)
    for trial in range(20):
        present = torch.randint(0, 6, (int(torch.randint(0, 30, (1,), generator=gen)),), generator=gen)
        offered = torch.randint(0, 8, (40,), generator=gen)
        candidates = torch.rand(40, generator=gen) < 0.7
        cap, finer = 1 + trial % 5, (1.0, 1.5)[trial % 2]
        got = capped_mask(present, offered, candidates, cap, finer)
        assert torch.equal(got, capped_mask_oracle(present, offered, candidates, cap, finer)), trial
    # an empty map keeps min(offered, cap) per voxel
    assert int(capped_mask(torch.zeros(0, dtype=torch.int64), torch.zeros(10, dtype=torch.int64),
                           torch.ones(10, dtype=torch.bool), 4).sum()) == 4


def test_voxel_keys_separate_voxels_and_group_points_inside_one():
    means = torch.tensor([[0.01, 0.01, 0.01], [0.09, 0.02, 0.05], [0.11, 0.0, 0.0], [-0.01, 0.0, 0.0],
                          [0.0, 0.0, -0.01], [5.0, -3.0, 2.0]])
    keys = voxel_keys(means, 0.1)
    assert keys[0] == keys[1]
    assert len(set(keys.tolist())) == 5


def sweep(gmap: GaussianMap, first_id: int, offset: float) -> None:
    """A camera passing along the plane (5 keyframes), `offset` shifting every pose a little."""
    for k in range(5):
        pose = camera_pose(0.25 * k + offset, 0.3 * offset, 0.02 * k)
        v = view(pose)
        gmap.add_keyframe(first_id + k, pose, intrinsics(), v["image"], voxelized_surfels(pose, 0), v["depth"])


def revisit_growth(cap: int) -> tuple[int, int, GaussianMap]:
    # The CPU RGB-D settings: no pruning, new surfels wherever the map covers a pixel less than 95 %.
    gmap = GaussianMap(MapConfig(window=2, voxel_cap=cap, thresholds=FusionThresholds(
        rgb_error=math.inf, depth_error=math.inf, tau_accum=0.95)))
    sweep(gmap, 0, 0.0)
    after_first = gmap.num_gaussians
    for first_id, offset in ((10, 0.04), (20, -0.03)):
        # refinement leaves surfels translucent: the map covers a revisited view less than the fusion threshold
        gmap.surfels.opacities.mul_(0.7)
        sweep(gmap, first_id, offset)
    return after_first, gmap.num_gaussians, gmap


def test_a_revisited_area_adds_no_surfels_beyond_the_voxel_cap():
    first, third, gmap = revisit_growth(cap=32)
    uncapped_first, uncapped_third, _ = revisit_growth(cap=0)
    assert first > 0.8 * uncapped_first  # the first pass maps the plane about as densely
    assert uncapped_third > 1.3 * uncapped_first, (uncapped_first, uncapped_third)  # without a cap it grows
    assert third < 1.03 * first, (first, third)  # with the cap it stays


def closer_view_added(cap: int) -> int:
    gmap = GaussianMap(MapConfig(window=2, voxel_cap=cap))
    far = camera_pose(0.0, 0.0, 0.0)
    v = view(far)
    gmap.add_keyframe(0, far, intrinsics(), v["image"], voxelized_surfels(far, 0), v["depth"])
    near = far @ torch.tensor([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.0], [0, 0, 0, 1]],
                              dtype=torch.float64)  # 1 m closer to the plane 2 m away: 4x the surfel density
    v = view(near)
    gmap.config.thresholds = FusionThresholds(tau_accum=1.0)  # fusion alone would add every surfel
    return gmap.add_keyframe(1, near, intrinsics(), v["image"], voxelized_surfels(near, 1), v["depth"]).added


def test_a_closer_view_still_adds_detail_up_to_the_cap():
    offered = WIDTH * HEIGHT // 4
    # the far view left ~16 surfels in each voxel, the near one offers ~64: it tops them up to min(64, cap)
    assert 0.65 * offered < closer_view_added(cap=128) < 0.85 * offered
    assert 0.2 * offered < closer_view_added(cap=32) < 0.4 * offered


def test_voxel_size_survives_a_snapshot():
    _, _, gmap = revisit_growth(cap=32)
    restored = GaussianMap.from_state_dict(unpack(pack(gmap.state_dict())))
    assert restored._voxel_size == gmap._voxel_size > 0
    pose = camera_pose(0.3, 0.0, 0.0)
    v = view(pose)
    stats = restored.add_keyframe(99, pose, intrinsics(), v["image"], voxelized_surfels(pose, 0), v["depth"])
    assert stats.added < 0.03 * (WIDTH * HEIGHT // 4)


def test_merge_renders_only_the_view_but_prunes_like_the_whole_map():
    """Surfels out of the new keyframe's view take no part in its merge; the result equals a whole-map merge."""
    gmap = GaussianMap(MapConfig(window=1, voxel_cap=0))
    far_away = camera_pose(40.0, 0.0, 0.0)
    v = view(far_away)
    gmap.add_keyframe(0, far_away, intrinsics(), v["image"], voxelized_surfels(far_away, 0), v["depth"])
    pose = camera_pose(0.0, 0.0, 0.0)
    v = view(pose)
    gmap.add_keyframe(1, pose, intrinsics(), v["image"], voxelized_surfels(pose, 1), v["depth"])
    count = gmap.num_gaussians
    # damage the surfels of keyframe 1: a third view of them prunes those, and none of keyframe 0's
    bad = gmap.surfels.keyframe_ids == 1
    gmap.surfels.colors[bad] = 1.0 - gmap.surfels.colors[bad]
    stats = gmap.add_keyframe(2, pose, intrinsics(), v["image"], voxelized_surfels(pose, 2), v["depth"])
    assert stats.pruned > 0.3 * int(bad.sum())
    assert int((gmap.surfels.keyframe_ids == 0).sum()) == count - int(bad.sum())


def test_global_refinement_stops_at_its_time_budget():
    gmap = GaussianMap(MapConfig(window=3, archived_images=4))
    for k in range(3):
        pose = camera_pose(0.3 * k, 0.0, 0.0)
        v = view(pose)
        gmap.add_keyframe(k, pose, intrinsics(), v["image"], voxelized_surfels(pose, k), v["depth"])
    gmap.refine(1)  # the first optimiser of a process imports much of torch: not part of the budget
    start = time.perf_counter()
    report = gmap.refine_global(100_000, budget_s=0.5)
    assert time.perf_counter() - start < 5.0
    assert 0 < len(report.losses) < 100_000
    assert len(gmap.refine_global(6, budget_s=math.inf).losses) == 6
    gmap.config.final_refine_budget_s = 0.0  # the config's budget is the default
    assert gmap.refine_global(6).losses == []
