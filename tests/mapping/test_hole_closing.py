"""Closing the holes of keyframes' views from the map's own geometry (worker.mapping.hole_closing), before the final
refinement: a view between keyframes that sees past their borders, or a keyframe region stereo left without depth,
has no hole afterwards, at the right depth and colour."""

import pytest
import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, pixel_surfels, psnr, view

from worker.eval.metrics import hole_shares
from worker.mapping import raster_gsplat
from worker.mapping.gaussian_map import GaussianMap, MapConfig
from worker.mapping.hole_closing import HoleClosingSettings

BORDER = 6  # pixels of each keyframe's border band stereo gave no depth (only that keyframe saw them)


def _stereo_surfels(pose: torch.Tensor, keyframe_id: int, hole: tuple[slice, slice] | None = None):
    """Per-pixel surfels of the plane, none in the border band (and none in `hole`): multi-view depth's output."""
    keep = torch.zeros(HEIGHT, WIDTH, dtype=torch.bool)
    keep[BORDER:-BORDER, BORDER:-BORDER] = True
    if hole is not None:
        keep[hole] = False
    surfels = pixel_surfels(pose).select(keep.reshape(-1))
    surfels.keyframe_ids = torch.full((len(surfels),), keyframe_id, dtype=torch.int64)
    return surfels


def _map(poses: list[torch.Tensor], hole: tuple[slice, slice] | None = None, device: str = "cpu") -> GaussianMap:
    gmap = GaussianMap(MapConfig(voxel_cap=0, final_refine_budget_s=None, device=device))
    for kf, pose in enumerate(poses):
        gmap.add_keyframe(kf, pose, intrinsics(), view(pose)["image"], _stereo_surfels(pose, kf, hole),
                          view(pose)["depth"])
    return gmap


def _render(gmap: GaussianMap, pose: torch.Tensor):
    return gmap.render(pose, intrinsics(), WIDTH, HEIGHT)


def test_a_view_past_the_keyframes_borders_has_no_hole_after_closing():
    """Two keyframes; a held-out view between them turned 4 degrees sees past both frames' borders (and their
    border bands had no depth): before, a hole of > 5 % of the image; after, none, and the closed region lies on the
    plane (rendered depth within 2 %)."""
    poses = [camera_pose(-0.05), camera_pose(0.05)]
    gmap = _map(poses)
    held_out = camera_pose(0.0, 0.03, yaw=0.07, pitch=-0.05)
    uncovered, largest = hole_shares(_render(gmap, held_out).alpha.numpy())
    assert largest > 0.05, largest
    added = gmap.close_holes(HoleClosingSettings(margin=0.15, reach=0.3))
    assert added > 0
    render = _render(gmap, held_out)
    uncovered, largest = hole_shares(render.alpha.numpy())
    assert uncovered == 0.0 and largest == 0.0, (uncovered, largest)
    truth = view(held_out)["depth"]
    relative = ((render.depth - truth).abs() / truth)
    assert float(relative.median()) < 0.005 and float(relative.max()) < 0.02, relative.max()


def test_a_hole_inside_a_keyframe_takes_the_keyframes_colours():
    """A patch both keyframes' stereo missed renders black before; after closing it has the photo's colours (the
    view's PSNR rises by more than 10 dB) at the plane's depth."""
    poses = [camera_pose(-0.05), camera_pose(0.05)]
    gmap = _map(poses, hole=(slice(16, 32), slice(20, 40)))
    target = camera_pose(0.0)
    image = view(target)["image"]
    before = psnr(_render(gmap, target).rgb, image)
    gmap.close_holes(HoleClosingSettings(margin=0.0, reach=0.3))
    render = _render(gmap, target)
    assert hole_shares(render.alpha.numpy())[1] == 0.0
    inner = (slice(18, 30), slice(22, 38))
    assert psnr(render.rgb[inner], image[inner]) > 25.0
    assert psnr(render.rgb, image) > before + 10.0, (before, psnr(render.rgb, image))
    truth = view(target)["depth"]
    assert float(((render.depth - truth).abs() / truth)[inner].max()) < 0.02


def test_closing_adds_nothing_where_the_map_already_covers_the_view():
    """A keyframe whose surfels cover its whole view (no margin asked) gets no new surfel; the final refinement
    closes holes only when the config asks for it."""
    pose = camera_pose(0.0)
    gmap = GaussianMap(MapConfig(voxel_cap=0))
    gmap.add_keyframe(0, pose, intrinsics(), view(pose)["image"], pixel_surfels(pose), view(pose)["depth"])
    assert gmap.close_holes(HoleClosingSettings(margin=0.0)) == 0
    count = gmap.num_gaussians
    gmap = _map([camera_pose(-0.05), camera_pose(0.05)])
    count = gmap.num_gaussians
    gmap.refine_global(iterations=1)
    assert gmap.num_gaussians <= count  # hole_closing off by default in MapConfig
    closing = _map([camera_pose(-0.05), camera_pose(0.05)])
    closing.config.hole_closing = HoleClosingSettings(margin=0.1)
    closing.refine_global(iterations=1)
    assert closing.num_gaussians > count


def test_a_view_the_map_barely_covers_is_left_alone():
    """A keyframe whose own stereo failed (a jump: its view holds only a sliver of the map) gets no surfels: its few
    covered pixels are no ground to extrapolate a whole view from."""
    pose = camera_pose(0.0)
    sliver = torch.zeros(HEIGHT, WIDTH, dtype=torch.bool)
    sliver[:, :12] = True  # a quarter of the view
    gmap = GaussianMap(MapConfig(voxel_cap=0))
    gmap.add_keyframe(0, pose, intrinsics(), view(pose)["image"], pixel_surfels(pose).select(sliver.reshape(-1)),
                      view(pose)["depth"])
    assert gmap.close_holes(HoleClosingSettings(margin=0.1, min_covered=0.5)) == 0
    assert gmap.close_holes(HoleClosingSettings(margin=0.1, min_covered=0.2, reach=0.1)) > 0


@pytest.mark.gpu
@pytest.mark.skipif(not raster_gsplat.available(), reason="needs CUDA and the gsplat package")
def test_closing_on_the_gpu_matches_the_cpu():
    """The same closing with the map on CUDA (gsplat renders): no hole left, the same depth as on the CPU."""
    poses = [camera_pose(-0.05), camera_pose(0.05)]
    held_out = camera_pose(0.0, 0.03, yaw=0.07, pitch=-0.05)
    depths = {}
    for device in ("cpu", "cuda"):
        gmap = _map(poses, device=device)
        assert gmap.close_holes(HoleClosingSettings(margin=0.15, reach=0.3)) > 0
        render = _render(gmap, held_out)
        uncovered, largest = hole_shares(render.alpha.cpu().numpy())
        assert uncovered == 0.0 and largest == 0.0, (device, uncovered, largest)
        depths[device] = render.depth.cpu()
    assert float(((depths["cuda"] - depths["cpu"]).abs() / depths["cpu"]).max()) < 0.01
