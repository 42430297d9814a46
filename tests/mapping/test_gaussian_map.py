import pytest
import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, psnr, view, voxelized_surfels

from protocol.codec import pack, unpack
from worker.geometry import make_sim3, so3_exp
from worker.mapping.gaussian_map import GaussianMap, MapConfig
from worker.mapping.ply import surfels_from_ply_bytes


def add(gmap: GaussianMap, kf_id: int, pose, with_depth: bool = True):
    v = view(pose)
    return gmap.add_keyframe(kf_id, pose, intrinsics(), v["image"], voxelized_surfels(pose, 99),
                             v["depth"] if with_depth else None)


def test_second_keyframe_adds_only_the_unseen_part_and_renders_well():
    gmap = GaussianMap(MapConfig(window=2))
    first = add(gmap, 0, camera_pose())
    assert first.pruned == 0 and first.added == gmap.num_gaussians == WIDTH * HEIGHT // 4
    assert set(gmap.surfels.keyframe_ids.tolist()) == {0}
    # camera moved right by 0.5 m at 2 m depth: ~15 of 64 columns are new
    pose1 = camera_pose(0.5, 0.0, 0.0, scale=1.3)
    second = add(gmap, 1, pose1)
    assert second.pruned < 20
    assert 0 < second.added < 0.45 * (WIDTH * HEIGHT // 4)
    assert second.added + second.skipped == WIDTH * HEIGHT // 4
    new = gmap.surfels.select(gmap.surfels.keyframe_ids == 1)
    assert float(new.means[:, 0].min()) > 0.3  # only right of the first view's field (x < ~0.53 + margin)
    assert float((new.means[:, 2] - 2.0).abs().max()) < 1e-4  # eq. 17 put them on the plane
    r = gmap.render(pose1, intrinsics(), WIDTH, HEIGHT)
    assert psnr(r.rgb, view(pose1)["image"]) > 20
    assert float(r.alpha.mean()) > 0.9


def test_refine_improves_the_window():
    gmap = GaussianMap(MapConfig(window=1, iterations=8))
    pose = camera_pose()
    add(gmap, 0, pose)
    gen = torch.Generator().manual_seed(0)
    gmap.surfels.colors.copy_((gmap.surfels.colors + 0.3 * torch.randn(gmap.surfels.colors.shape, generator=gen))
                              .clamp(0, 1))
    before = psnr(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, view(pose)["image"])
    report = gmap.refine()
    after = psnr(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, view(pose)["image"])
    assert len(report.losses) == 8
    assert after > before + 1.0, (before, after)


def test_pose_updates_move_the_map_with_its_keyframe():
    gmap = GaussianMap()
    # yaw and pitch: no two surfels share a depth, so float rounding cannot reorder exact depth ties
    pose = camera_pose(0.1, 0.0, 0.15, pitch=0.1)
    add(gmap, 3, pose)
    before = gmap.render(pose, intrinsics(), WIDTH, HEIGHT)
    new_pose = make_sim3(so3_exp(torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)),
                         torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64), 1.7) @ pose
    gmap.apply_pose_updates({3: new_pose})
    assert torch.allclose(gmap.keyframe_pose(3), new_pose)
    after = gmap.render(new_pose, intrinsics(), WIDTH, HEIGHT)
    # the same image up to float32 rounding (which can tip a few near-threshold blending decisions)
    assert float((after.rgb - before.rgb).abs().mean()) < 1e-3
    assert float((after.alpha - before.alpha).abs().mean()) < 1e-3
    covered = before.alpha > 0.5
    depth_ratio = after.depth[covered] / before.depth[covered]  # world units scale with s
    assert float((depth_ratio - 1.7).abs().median()) < 1e-3
    with pytest.raises(ValueError, match="unknown keyframe"):
        gmap.apply_pose_updates({42: new_pose})


def test_state_dict_round_trip_through_msgpack_and_ply():
    gmap = GaussianMap(MapConfig(window=1))
    add(gmap, 0, camera_pose())
    add(gmap, 1, camera_pose(0.3, 0.0, 0.0), with_depth=False)
    restored = GaussianMap.from_state_dict(unpack(pack(gmap.state_dict())))
    assert restored.num_gaussians == gmap.num_gaussians and restored.keyframe_ids == [0, 1]
    for name, value in gmap.surfels.tensors().items():
        assert torch.equal(getattr(restored.surfels, name), value), name
    assert torch.equal(restored.keyframe_pose(1), gmap.keyframe_pose(1))
    assert restored.config == gmap.config
    ply = surfels_from_ply_bytes(gmap.to_ply_bytes())
    assert len(ply) == gmap.num_gaussians
    assert torch.allclose(ply.means, gmap.surfels.means, atol=1e-6)
    with pytest.raises(ValueError, match="version"):
        GaussianMap().load_state_dict({"version": 99})


def test_bad_input_is_rejected():
    gmap = GaussianMap()
    add(gmap, 0, camera_pose())
    with pytest.raises(ValueError, match="already"):
        add(gmap, 0, camera_pose())
    pose = camera_pose()
    surfels = voxelized_surfels(pose)
    with pytest.raises(ValueError, match="image"):
        gmap.add_keyframe(1, pose, intrinsics(), torch.zeros(HEIGHT, WIDTH), surfels)
    with pytest.raises(ValueError, match="pose"):
        gmap.add_keyframe(1, torch.eye(3), intrinsics(), torch.zeros(HEIGHT, WIDTH, 3), surfels)
    with pytest.raises(ValueError, match="depth"):
        gmap.add_keyframe(1, pose, intrinsics(), torch.zeros(HEIGHT, WIDTH, 3), surfels, torch.zeros(3, 3))


def test_numpy_inputs_and_intrinsics_object_are_accepted():
    from worker.geometry import Intrinsics

    pose = camera_pose()
    v = view(pose)
    gmap = GaussianMap()
    image_u8 = (v["image"] * 255).round().to(torch.uint8).numpy()
    intr = Intrinsics.from_matrix(intrinsics(), WIDTH, HEIGHT)
    gmap.add_keyframe(0, pose.numpy(), intr, image_u8, voxelized_surfels(pose), v["depth"].numpy())
    a = gmap.render(pose.numpy(), intr, WIDTH, HEIGHT)
    b = gmap.render(pose, intrinsics(), WIDTH, HEIGHT)
    assert torch.equal(a.rgb, b.rgb)
    assert psnr(a.rgb, v["image"]) > 20


def test_archive_keeps_old_keyframe_images_compact_and_thinned():
    gmap = GaussianMap(MapConfig(window=1, archived_images=2))
    xs = [0.0, 0.2, 0.21, 0.5, 0.6]  # keyframes 1 and 2 see nearly the same view, 3 and 4 nearly
    for k, x in enumerate(xs):
        add(gmap, k, camera_pose(x, 0.0, 0.0))
    held = {k: gmap._keyframes[k] for k in gmap.keyframe_ids if gmap._keyframes[k].held}
    # the window's keyframe stays raw; 4 left the window, thinned 4 -> 2 as they came, the most redundant view
    # first: the older of the near twins, then keyframe 3, which the window's keyframe sees nearly as it did
    # (halving the archive kept 1, 3, 4)
    assert sorted(held) == [0, 2, 4] and gmap.held_images == 3
    assert held[4].image.dtype == torch.float32 and held[4].archived is None
    assert held[2].image is None and held[2].archived is not None
    raw_bytes = held[4].image.numel() * 4 + held[4].depth.numel() * 4
    archived_bytes = len(held[2].archived.jpeg) + held[2].archived.depth.nbytes
    assert archived_bytes < raw_bytes / 4
    # what refinement sees of an archived keyframe is close to what it saw raw
    image, depth = held[2].archived.unpack()
    original = view(camera_pose(xs[2], 0.0, 0.0))
    assert psnr(image, original["image"]) > 35
    assert image.shape == original["image"].shape and depth.shape == original["depth"].shape
    assert float((depth - original["depth"]).abs().max()) < 0.05
    restored = GaussianMap.from_state_dict(unpack(pack(gmap.state_dict())))
    assert restored.held_images == 3 and restored._keyframes[0].archived.jpeg == held[0].archived.jpeg
    without_archive = GaussianMap(MapConfig(window=1))
    for k in range(3):
        add(without_archive, k, camera_pose(0.1 * k, 0.0, 0.0))
    assert without_archive.held_images == 1


def test_global_refinement_fixes_views_the_window_has_left():
    poses = [camera_pose(0.0, 0.0, 0.0), camera_pose(0.9, 0.0, 0.0), camera_pose(1.8, 0.0, 0.0)]

    def damaged_map(archived: int) -> GaussianMap:
        gmap = GaussianMap(MapConfig(window=1, archived_images=archived))
        for k, pose in enumerate(poses):
            add(gmap, k, pose)
        gen = torch.Generator().manual_seed(1)
        noise = 0.3 * torch.randn(gmap.surfels.colors.shape, generator=gen)
        gmap.surfels.colors.copy_((gmap.surfels.colors + noise).clamp(0, 1))
        return gmap

    def first_view_psnr(gmap: GaussianMap) -> float:
        return psnr(gmap.render(poses[0], intrinsics(), WIDTH, HEIGHT).rgb, view(poses[0])["image"])

    gmap = damaged_map(archived=8)
    before = first_view_psnr(gmap)
    report = gmap.refine_global(12, seed=3)
    assert len(report.losses) == 12 and set(report.views) == {0, 1, 2}
    refined = first_view_psnr(gmap)
    window_only = damaged_map(archived=0)
    window_only.refine_global(12)  # only the newest keyframe's image is held: it fixes only what it overlaps
    assert refined > max(before, first_view_psnr(window_only)) + 1.0, (before, refined, first_view_psnr(window_only))


def test_refine_can_also_train_random_archived_keyframes():
    poses = [camera_pose(0.0, 0.0, 0.0), camera_pose(0.9, 0.0, 0.0), camera_pose(1.8, 0.0, 0.0)]

    def first_view_psnr_after_refine(archived_views: int) -> tuple[float, float, int]:
        gmap = GaussianMap(MapConfig(window=1, archived_images=8, archived_views_per_refine=archived_views))
        for k, pose in enumerate(poses):
            add(gmap, k, pose)
        gen = torch.Generator().manual_seed(1)
        noise = 0.3 * torch.randn(gmap.surfels.colors.shape, generator=gen)
        gmap.surfels.colors.copy_((gmap.surfels.colors + noise).clamp(0, 1))
        before = psnr(gmap.render(poses[0], intrinsics(), WIDTH, HEIGHT).rgb, view(poses[0])["image"])
        report = gmap.refine(12)
        after = psnr(gmap.render(poses[0], intrinsics(), WIDTH, HEIGHT).rgb, view(poses[0])["image"])
        return before, after, len(set(report.views))

    before, window_only, views = first_view_psnr_after_refine(0)
    assert views == 1 and window_only < before + 0.5
    _, with_archived, views = first_view_psnr_after_refine(2)
    assert views == 3 and with_archived > window_only + 1.0, (before, window_only, with_archived)
