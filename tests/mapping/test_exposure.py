"""Per-keyframe affine exposure: estimated during fusion and refinement, removed from the map's colours."""

import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, psnr, view, voxelized_surfels

from worker.mapping.exposure import apply_exposure, fit_exposure, identity_exposure, remove_exposure
from worker.mapping.gaussian_map import GaussianMap, MapConfig
from worker.mapping.refine import RefineSettings
from worker.serialization import pack, unpack

GAIN, BIAS = torch.tensor([1.25, 1.15, 1.3]), torch.tensor([0.01, -0.01, 0.0])
BRIGHT = torch.cat([GAIN, BIAS])
POSES = [camera_pose(0.0), camera_pose(0.12), camera_pose(0.24, 0.05), camera_pose(0.1, 0.12), camera_pose(0.6, 0.1)]
BRIGHT_KEYFRAME = 4  # it sees a third of its view for the first time


def _photo(kf: int) -> torch.Tensor:
    image = view(POSES[kf])["image"]
    return apply_exposure(image, BRIGHT).clamp(0, 1) if kf == BRIGHT_KEYFRAME else image


def _surfels(kf: int):
    """The keyframe's surfels coloured by its own photo, as the frontend makes them."""
    surfels = voxelized_surfels(POSES[kf], kf)
    if kf == BRIGHT_KEYFRAME:
        surfels.colors = apply_exposure(surfels.colors, BRIGHT).clamp(0, 1)
    return surfels


def _map(exposure: bool) -> GaussianMap:
    gmap = GaussianMap(MapConfig(window=3, iterations=15, voxel_cap=0, refine=RefineSettings(exposure=exposure)))
    for kf in range(len(POSES)):
        gmap.add_keyframe(kf, POSES[kf], intrinsics(), _photo(kf), _surfels(kf), view(POSES[kf])["depth"])
        gmap.refine()
    return gmap


def test_fit_recovers_an_affine_exposure_and_falls_back_without_pixels():
    image = view(camera_pose())["image"]
    photo = apply_exposure(image, BRIGHT)
    fitted = fit_exposure(image, photo, torch.ones(HEIGHT, WIDTH, dtype=torch.bool), prior=0.0, bias_prior=0.0)
    assert torch.allclose(fitted, BRIGHT, atol=1e-4)
    assert torch.allclose(remove_exposure(photo, fitted), image, atol=1e-4)
    assert fit_exposure(image, photo, torch.zeros(HEIGHT, WIDTH, dtype=torch.bool)) is None
    # the prior pulls toward the identity: on a flat image (no contrast) the gain stays near 1
    flat = torch.full_like(image, 0.5)
    weak = fit_exposure(flat, flat * 1.2, torch.ones(HEIGHT, WIDTH, dtype=torch.bool))
    assert (weak[:3] - 1).abs().max() < 0.25


def test_a_brightened_keyframe_is_removed_from_the_map_colours():
    gmap = _map(exposure=True)
    plain = _map(exposure=False)
    # the gain of the brightened keyframe is recovered; the others stay near the identity; the first is fixed
    estimated = gmap.keyframe_exposure(BRIGHT_KEYFRAME)
    assert torch.allclose(estimated[:3], GAIN, atol=0.05), estimated
    assert torch.allclose(estimated[3:], BIAS, atol=0.02), estimated
    for kf in (1, 2, 3):
        assert (gmap.keyframe_exposure(kf) - identity_exposure()).abs().max() < 0.05, gmap.keyframe_exposure(kf)
    assert torch.equal(gmap.keyframe_exposure(0), identity_exposure())
    # a render at the brightened keyframe's pose shows the normalised colours, not its photo's
    pose = POSES[BRIGHT_KEYFRAME]
    truth = view(pose)["image"]
    with_exposure = psnr(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, truth)
    without = psnr(plain.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, truth)
    assert with_exposure > 28 and with_exposure > without + 5, (with_exposure, without)
    # ... and under its exposure it matches the photo
    photo_match = psnr(apply_exposure(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, estimated),
                       _photo(BRIGHT_KEYFRAME))
    assert photo_match > 28, photo_match


def test_exposures_survive_a_snapshot():
    gmap = _map(exposure=True)
    restored = GaussianMap.from_state_dict(unpack(pack(gmap.state_dict())))
    for kf in gmap.keyframe_ids:
        assert torch.allclose(restored.keyframe_exposure(kf), gmap.keyframe_exposure(kf))
    assert restored.config.refine.exposure
