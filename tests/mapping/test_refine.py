import pytest
import torch
from mapping_scene import camera_pose, intrinsics, psnr, view, voxelized_surfels

from worker.mapping import Surfels
from worker.mapping.gaussian_map import rigid_viewmat
from worker.mapping.rasterize import rasterize, visible_mask
from worker.mapping.refine import RefineSettings, RefineView, refine_surfels


def make_views(poses):
    views = []
    for pose in poses:
        viewmat, s = rigid_viewmat(pose)
        v = view(pose)
        views.append(RefineView(viewmat.float(), intrinsics(), v["image"], v["depth"], s))
    return views


def perturbed_map(gen: torch.Generator) -> tuple[Surfels, Surfels]:
    pose = camera_pose()
    clean = voxelized_surfels(pose).transform(pose.float())
    noisy = clean.clone()
    noisy.colors = (noisy.colors + 0.25 * torch.randn(noisy.colors.shape, generator=gen)).clamp(0, 1)
    noisy.opacities = noisy.opacities * (0.5 + 0.5 * torch.rand(len(noisy), generator=gen))
    noisy.means = noisy.means + 0.01 * torch.randn(noisy.means.shape, generator=gen)
    return clean, noisy


def render_psnr(surfels: Surfels, views: list[RefineView]) -> float:
    with torch.no_grad():
        return sum(psnr(rasterize(surfels, v.viewmat, v.K, 64, 48).rgb, v.image) for v in views) / len(views)


def test_refinement_raises_psnr_of_a_perturbed_map():
    gen = torch.Generator().manual_seed(0)
    _, noisy = perturbed_map(gen)
    views = make_views([camera_pose(), camera_pose(0.1, 0.0, 0.05)])
    before = render_psnr(noisy, views)
    refined, report = refine_surfels(noisy, torch.ones(len(noisy), dtype=torch.bool), views, iterations=12)
    after = render_psnr(refined, views)
    assert len(report.losses) == 12 and report.views[:3] == [1, 0, 1]
    assert after > before + 1.5, (before, after)
    assert sum(report.losses[-4:]) < sum(report.losses[:4])
    assert len(refined) == len(noisy)


def test_refinement_leaves_the_torch_thread_count_as_it_was():
    _, noisy = perturbed_map(torch.Generator().manual_seed(4))
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        refine_surfels(noisy, torch.ones(len(noisy), dtype=torch.bool), make_views([camera_pose()]), iterations=2)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_only_the_window_is_optimised():
    gen = torch.Generator().manual_seed(1)
    _, noisy = perturbed_map(gen)
    trainable = torch.arange(len(noisy)) % 2 == 0
    refined, _ = refine_surfels(noisy, trainable, make_views([camera_pose()]), iterations=3)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(refined, name)[~trainable], getattr(noisy, name)[~trainable]), name
        assert not torch.equal(getattr(refined, name)[trainable], getattr(noisy, name)[trainable]), name
    assert float(refined.colors.min()) >= 0 and float(refined.colors.max()) <= 1


def test_bad_arguments():
    _, noisy = perturbed_map(torch.Generator().manual_seed(2))
    with pytest.raises(ValueError, match="trainable"):
        refine_surfels(noisy, torch.ones(3, dtype=torch.bool), make_views([camera_pose()]))
    with pytest.raises(ValueError, match="iterations"):
        refine_surfels(noisy, torch.ones(len(noisy), dtype=torch.bool), make_views([camera_pose()]), iterations=-1)


def test_surfels_no_view_can_draw_stay_untouched_and_ssim_resolution_is_a_setting():
    gen = torch.Generator().manual_seed(3)
    _, noisy = perturbed_map(gen)
    behind = noisy.select(torch.arange(5)).clone()
    behind.means = behind.means - 100.0 * torch.tensor([0.0, 0.0, 1.0])  # far behind every camera
    scene = Surfels.concat([noisy, behind])
    views = make_views([camera_pose()])
    assert not visible_mask(behind, views[0].viewmat, views[0].K, 64, 48).any()
    for factor in (1, 2):
        refined, report = refine_surfels(scene, torch.ones(len(scene), dtype=torch.bool), views, iterations=3,
                                         settings=RefineSettings(ssim_downsample=factor))
        assert len(report.losses) == 3
        for name in ("means", "quats", "scales", "opacities", "colors"):
            assert torch.equal(getattr(refined, name)[-5:], getattr(behind, name)), name
            assert not torch.equal(getattr(refined, name)[:-5], getattr(noisy, name)), name
    with pytest.raises(ValueError, match="ssim_downsample"):
        refine_surfels(scene, torch.ones(len(scene), dtype=torch.bool), views, iterations=1,
                       settings=RefineSettings(ssim_downsample=0))


def test_a_learning_rate_schedule_scales_the_steps():
    """A decay to a tiny factor moves the map less than constant rates, and more than tiny rates throughout; a
    non-positive factor is refused."""
    _, noisy = perturbed_map(torch.Generator().manual_seed(2))
    views = make_views([camera_pose(), camera_pose(0.1, 0.0, 0.05)])
    everything = torch.ones(len(noisy), dtype=torch.bool)

    def moved(schedule) -> float:
        refined, _ = refine_surfels(noisy, everything, views, iterations=8, lr_schedule=schedule)
        return float((refined.colors - noisy.colors).abs().mean())

    constant, decayed, tiny = moved(None), moved(lambda it: 1e-4 ** (it / 8)), moved(lambda it: 1e-4)
    assert tiny < 0.01 * constant and tiny < decayed < constant, (tiny, decayed, constant)
    with pytest.raises(ValueError, match="positive"):
        refine_surfels(noisy, everything, views, iterations=2, lr_schedule=lambda it: 0.0)
