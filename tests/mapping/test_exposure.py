"""Per-keyframe affine exposure: estimated during fusion and refinement, removed from the map's colours."""

import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, psnr, texture, view, voxelized_surfels

from protocol.codec import pack, unpack
from worker.mapping.exposure import apply_exposure, fit_exposure, identity_exposure, remove_exposure, shrink_exposure
from worker.mapping.gaussian_map import GaussianMap, MapConfig
from worker.mapping.refine import RefineSettings

GAIN, BIAS = torch.tensor([1.25, 1.15, 1.3]), torch.tensor([0.01, -0.01, 0.0])  # the fit estimates gains only
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
    """The five keyframes mapped with per-channel exposures (BRIGHT is a gain per channel)."""
    refine = RefineSettings(exposure=exposure, exposure_shared=False)
    gmap = GaussianMap(MapConfig(window=3, iterations=15, voxel_cap=0, refine=refine))
    for kf in range(len(POSES)):
        gmap.add_keyframe(kf, POSES[kf], intrinsics(), _photo(kf), _surfels(kf), view(POSES[kf])["depth"])
        gmap.refine()
    return gmap


def test_fit_recovers_a_gain_per_channel_and_falls_back_without_pixels():
    image = view(camera_pose())["image"]
    photo = image * GAIN
    fitted = fit_exposure(image, photo, torch.ones(HEIGHT, WIDTH, dtype=torch.bool), prior=0.0)
    assert torch.allclose(fitted, torch.cat([GAIN, torch.zeros(3)]), atol=1e-4)
    assert torch.allclose(remove_exposure(photo, fitted), image, atol=1e-4)
    assert fit_exposure(image, photo, torch.zeros(HEIGHT, WIDTH, dtype=torch.bool)) is None


def test_fit_ignores_view_dependent_tiles_and_render_noise():
    """The closed form: a quarter of the view brightened beyond the exposure (gloss seen from a new angle) and
    zero-mean noise in the render (misalignment) leave the median-tile gain within 1 %, where a least-squares gain
    moves by more than 3 % (what made ICL's keyframe gains drift)."""
    rows, cols = torch.meshgrid(torch.linspace(-1, 1, 240), torch.linspace(-1.3, 1.3, 320), indexing="ij")
    render = texture(torch.stack([cols, rows], -1))  # [240, 320, 3], smooth, in [0.1, 0.9]
    photo = render * GAIN
    photo[:, :80] *= 1.2  # view-dependent: not the exposure
    noisy = render + 0.05 * torch.randn(render.shape, generator=torch.Generator().manual_seed(0))
    covered = torch.ones(240, 320, dtype=torch.bool)
    fitted = fit_exposure(noisy, photo.clamp(0, 1), covered, prior=0.0)
    assert (fitted[:3] - GAIN).abs().max() < 0.01, fitted
    least_squares = (noisy * photo).sum((0, 1)) / (noisy * noisy).sum((0, 1))
    assert (least_squares - GAIN).abs().max() > 0.03, least_squares


def test_a_shared_gain_follows_the_brightness_and_leaves_a_colour_cast_alone():
    """One gain for the three channels: an exposure change (every channel alike) is recovered; a shift of white
    balance (red up, blue down, brightness kept) is not an exposure and leaves the identity after the shrinkage,
    where per-channel gains take it as one (and, on real footage, drift into hues from keyframe to keyframe)."""
    image = view(camera_pose())["image"]
    covered = torch.ones(HEIGHT, WIDTH, dtype=torch.bool)
    brighter = fit_exposure(image, (image * 1.2).clamp(0, 1), covered, prior=0.0, shared=True)
    assert torch.allclose(brighter[:3], torch.full((3,), 1.2), atol=0.01) and torch.equal(brighter[3:], torch.zeros(3))
    cast = image * torch.tensor([1.08, 1.0, 0.92])
    luminance_kept = cast * (image.sum() / cast.sum())
    shared = fit_exposure(image, luminance_kept, covered, prior=0.0, threshold=0.03, shared=True)
    per_channel = fit_exposure(image, luminance_kept, covered, prior=0.0, threshold=0.03)
    assert torch.equal(shared, identity_exposure()), shared
    assert per_channel[0] > 1.04 and per_channel[2] < 0.96, per_channel


def test_small_exposure_changes_are_shrunk_to_none_and_large_ones_kept():
    small = torch.tensor([1.02, 0.98, 1.0, 0.0, 0.0, 0.0])
    assert torch.equal(shrink_exposure(small, 0.03), identity_exposure())
    large = shrink_exposure(BRIGHT, 0.03)
    assert ((GAIN - large[:3]) > 0).all() and ((GAIN - large[:3]) < 0.01).all(), large
    assert torch.equal(shrink_exposure(BRIGHT, 0.0), BRIGHT)


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


def test_a_keyframe_merged_with_a_stale_exposure_is_re_estimated_against_the_rest_of_the_map():
    """A keyframe merged under load shedding keeps its exposure at arrival; estimate_exposure (catch-up, final
    refinement) fits it against the map without its own surfels and re-normalises them."""
    state = _map(exposure=True).state_dict()
    entry = next(e for e in state["keyframes"] if e["id"] == BRIGHT_KEYFRAME)
    entry["exposure"] = identity_exposure().numpy()  # stale: its surfels carry the photo's brightened colours
    own = state["surfels"]["keyframe_ids"] == BRIGHT_KEYFRAME
    state["surfels"]["colors"][own] = apply_exposure(torch.from_numpy(state["surfels"]["colors"][own]),
                                                     BRIGHT).clamp(0, 1).numpy()
    gmap = GaussianMap.from_state_dict(state)
    pose, truth = POSES[BRIGHT_KEYFRAME], view(POSES[BRIGHT_KEYFRAME])["image"]
    stale = psnr(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, truth)
    assert gmap.estimate_exposure(BRIGHT_KEYFRAME)
    assert torch.allclose(gmap.keyframe_exposure(BRIGHT_KEYFRAME)[:3], GAIN, atol=0.05)
    fixed = psnr(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, truth)
    assert fixed > 28 and fixed > stale + 5, (stale, fixed)
    assert not gmap.estimate_exposure(0)  # the first keyframe fixes the map's colour scale


def test_exposure_changes_over_a_sequence_merged_without_refinement_are_removed():
    """Every keyframe merged without refinement (load shedding), each with its own gain, then the final
    refinement: the gains are recovered and renders show the unchanged colours at every pose."""
    gains = [1.0, 1.12, 0.88, 1.2, 0.9]

    def build(exposure: bool) -> GaussianMap:
        gmap = GaussianMap(MapConfig(window=3, iterations=15, voxel_cap=0, refine=RefineSettings(exposure=exposure)))
        for kf, gain in enumerate(gains):
            surfels = voxelized_surfels(POSES[kf], kf)
            surfels.colors = (surfels.colors * gain).clamp(0, 1)
            photo = (view(POSES[kf])["image"] * gain).clamp(0, 1)
            gmap.add_keyframe(kf, POSES[kf], intrinsics(), photo, surfels, view(POSES[kf])["depth"])
        gmap.refine_global(iterations=4 * len(gains), budget_s=float("inf"))
        return gmap

    gmap, plain = build(True), build(False)
    for kf, gain in enumerate(gains):
        assert abs(float(gmap.keyframe_exposure(kf)[0]) - gain) < 0.05, (kf, gmap.keyframe_exposure(kf))
    truth = [view(pose)["image"] for pose in POSES]
    ours = [psnr(gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, t) for pose, t in zip(POSES, truth)]
    theirs = [psnr(plain.render(pose, intrinsics(), WIDTH, HEIGHT).rgb, t) for pose, t in zip(POSES, truth)]
    assert min(ours) > 28 and sum(ours) / len(ours) > sum(theirs) / len(theirs) + 5, (ours, theirs)


def test_the_exposure_of_a_frame_between_keyframes_is_interpolated_and_renders_as_its_photo():
    """Keyframes at frames 0, 10, 20, 30, 40 with their own gains: a frame between two has the exposure between
    theirs (log gains linear in the frame index), the ends keep their nearest keyframe's; a render "as captured" at
    a held-out frame under auto-exposure matches its photo where the normalised render does not."""
    from worker.config import MappingConfig as EngineMappingConfig
    from worker.mapping.exposure import interpolate_exposure
    from worker.pipeline.mapping_stage import MappingStage

    gains = [1.0, 0.75, 0.75, 0.6, 0.6]  # the camera darkens
    stage = MappingStage(EngineMappingConfig(refine_keyframes=3, refine_iterations=15, voxel_cap=0), threaded=False,
                         max_backlog=4)
    for kf, gain in enumerate(gains):
        surfels = voxelized_surfels(POSES[kf], kf)
        surfels.colors = (surfels.colors * gain).clamp(0, 1)
        photo = (view(POSES[kf])["image"] * gain).clamp(0, 1)
        stage.map.add_keyframe(10 * kf, POSES[kf], intrinsics(), photo, surfels, view(POSES[kf])["depth"])
    stage.map.refine_global(iterations=4 * len(gains), budget_s=float("inf"))
    gmap = stage.map
    assert torch.equal(gmap.exposure_at(10), gmap.keyframe_exposure(10))
    assert torch.equal(gmap.exposure_at(-3), gmap.keyframe_exposure(0))
    assert torch.equal(gmap.exposure_at(75), gmap.keyframe_exposure(40))
    midway = gmap.exposure_at(25)
    expected = interpolate_exposure(gmap.keyframe_exposure(20), gmap.keyframe_exposure(30), 0.5)
    assert torch.allclose(midway, expected)
    assert abs(float(midway[0]) - (0.75 * 0.6) ** 0.5) < 0.06, midway  # the geometric mean of the two gains
    # a held-out frame 25 at keyframe 3's pose, photographed with the gain between its neighbours'
    pose = POSES[3]
    photo = (view(pose)["image"] * (0.75 * 0.6) ** 0.5).clamp(0, 1)
    captured = stage.render(pose, intrinsics(), WIDTH, HEIGHT, as_captured_at=25).rgb
    normalised = stage.render(pose, intrinsics(), WIDTH, HEIGHT).rgb
    assert psnr(captured, photo) > 28 and psnr(captured, photo) > psnr(normalised, photo) + 3, (
        psnr(captured, photo), psnr(normalised, photo))
    assert torch.equal(normalised, gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb)
