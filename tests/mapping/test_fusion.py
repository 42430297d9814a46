import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, pixel_surfels, view

from worker.geometry import project_points
from worker.mapping import Surfels
from worker.mapping.fusion import FusionThresholds, attribute_errors, densify_mask, prune_mask
from worker.mapping.gaussian_map import rigid_viewmat


def world_map():
    pose = camera_pose()
    return pose, pixel_surfels(pose).transform(pose.float())


def pixels_of(surfels: Surfels, pose) -> torch.Tensor:
    viewmat, _ = rigid_viewmat(pose)
    cam = surfels.means.double() @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv, _ = project_points(cam, intrinsics().double())
    return uv


def test_weights_sum_to_accumulation():
    pose, surfels = world_map()
    v = view(pose)
    image = v["image"].clone()
    image[10:20, 10:30] = 1.0 - image[10:20, 10:30]
    viewmat, _ = rigid_viewmat(pose)
    att = attribute_errors(surfels, viewmat.float(), intrinsics(), image, None, FusionThresholds())
    # sum_i w_ip = alpha_p, so per-surfel weights must add up to the accumulation over (bad) pixels
    assert abs(float(att.total_weight.sum()) - float(att.render.alpha.sum())) < 1e-2 * float(att.render.alpha.sum())
    bad_alpha = float(att.render.alpha[att.bad_pixels].sum())
    assert bad_alpha > 50
    assert abs(float(att.bad_weight.sum()) - bad_alpha) < 1e-2 * bad_alpha


def test_rgb_error_prunes_only_the_changed_region():
    pose, surfels = world_map()
    image = view(pose)["image"].clone()
    image[10:20, 10:30] = torch.tensor([1.0, 0.0, 1.0])  # magenta patch the map does not explain
    viewmat, _ = rigid_viewmat(pose)
    th = FusionThresholds()
    att = attribute_errors(surfels, viewmat.float(), intrinsics(), image, None, th)
    remove = prune_mask(att, th)
    uv = pixels_of(surfels, pose)
    inside = (uv[:, 0] > 10) & (uv[:, 0] < 30) & (uv[:, 1] > 10) & (uv[:, 1] < 20)
    near = (uv[:, 0] > 8) & (uv[:, 0] < 32) & (uv[:, 1] > 8) & (uv[:, 1] < 22)
    assert int(remove.sum()) > 0
    assert not bool((remove & ~near).any()), "pruned a surfel far from the changed patch"
    core = (uv[:, 0] > 11) & (uv[:, 0] < 29) & (uv[:, 1] > 11) & (uv[:, 1] < 19)
    assert float(remove[core].float().mean()) > 0.95
    assert int(remove.sum()) <= int(near.sum()) and int(inside.sum()) > 0


def test_depth_error_prunes_floaters():
    pose, plane = world_map()
    v = view(pose)
    gen = torch.Generator().manual_seed(0)
    n = 12
    floater_px = torch.stack([torch.randint(8, WIDTH - 8, (n,), generator=gen),
                              torch.randint(8, HEIGHT - 8, (n,), generator=gen)], dim=-1)
    z = 1.0
    x = (floater_px[:, 0] + 0.5 - WIDTH / 2) / 60.0 * z
    y = (floater_px[:, 1] + 0.5 - HEIGHT / 2) / 60.0 * z
    means = torch.stack([x, y, torch.full((n,), z)], dim=-1)
    floaters = Surfels(means, torch.tensor([1.0, 0, 0, 0]).repeat(n, 1), torch.full((n, 2), 2.0 / 60.0),
                       torch.full((n,), 0.9), v["image"][floater_px[:, 1], floater_px[:, 0]],
                       torch.full((n,), 1, dtype=torch.int64))
    surfels = Surfels.concat([plane, floaters])
    viewmat, _ = rigid_viewmat(pose)
    th = FusionThresholds()
    no_depth = prune_mask(attribute_errors(surfels, viewmat.float(), intrinsics(), v["image"], None, th), th)
    assert int(no_depth[len(plane):].sum()) < n  # colour alone does not reveal them
    att = attribute_errors(surfels, viewmat.float(), intrinsics(), v["image"], v["depth"], th)
    remove = prune_mask(att, th)
    assert bool(remove[len(plane):].all())
    assert float(remove[: len(plane)].float().mean()) < 0.05


def test_densify_only_where_accumulation_is_low():
    pose = camera_pose()
    cam = pixel_surfels(pose)
    acc = torch.ones(HEIGHT, WIDTH)
    acc[:, WIDTH // 2:] = 0.2
    add = densify_mask(cam, intrinsics(), acc, tau_accum=0.7)
    uv, _ = project_points(cam.means, intrinsics())
    assert torch.equal(add, uv[:, 0] >= WIDTH // 2)
    behind = cam.clone()
    behind.means[:, 2] = -1.0
    assert not bool(densify_mask(behind, intrinsics(), acc, 0.7).any())
