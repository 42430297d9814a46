"""The map's background (worker.mapping.background): colour by world direction of what keyframes saw through the map's
holes, composited behind the surfels in renders and refinement."""

from __future__ import annotations

import math

import torch
from mapping_scene import HEIGHT, WIDTH, camera_pose, intrinsics, psnr, view, voxelized_surfels

from protocol.codec import pack, unpack
from worker.geometry import make_sim3, so3_exp
from worker.mapping.background import DirectionalBackground, pixel_directions
from worker.mapping.gaussian_map import GaussianMap, MapConfig


def sky(directions: torch.Tensor) -> torch.Tensor:
    """A smooth colour per world direction (a sky that depends on where one looks, not from where)."""
    return (0.5 + 0.4 * directions).to(torch.float32)


def turned(yaw: float, pitch: float = 0.0, position=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return make_sim3(so3_exp(torch.tensor([pitch, yaw, 0.0], dtype=torch.float64)),
                     torch.tensor(position, dtype=torch.float64), 1.0)


def test_directions_seen_through_holes_come_back_from_any_position() -> None:
    background = DirectionalBackground()
    K = intrinsics()
    first = turned(0.0)
    alpha = torch.zeros(HEIGHT, WIDTH)
    alpha[:, : WIDTH // 2] = 1.0  # the map covers the left half: only the right half shows the sky
    taken = background.observe(first, K, sky(pixel_directions(first, K, WIDTH, HEIGHT)), alpha)
    assert taken == HEIGHT * WIDTH // 2
    # a camera far away, turned 15 degrees right, scaled (a Sim(3) pose): the directions it shares see the same sky
    later = make_sim3(so3_exp(torch.tensor([0.0, 0.26, 0.0], dtype=torch.float64)),
                      torch.tensor([40.0, -3.0, 25.0], dtype=torch.float64), 2.5)
    image = background.image(later, K, WIDTH, HEIGHT)
    directions = pixel_directions(later, K, WIDTH, HEIGHT)
    in_first = directions.to(torch.float64) @ first[:3, :3]  # the directions in the first camera's frame
    u = K[0, 0] * in_first[..., 0] / in_first[..., 2] + K[0, 2]
    v = K[1, 1] * in_first[..., 1] / in_first[..., 2] + K[1, 2]
    shared = (in_first[..., 2] > 0) & (u > WIDTH // 2 + 2) & (u < WIDTH - 2) & (v > 2) & (v < HEIGHT - 2)
    assert int(shared.sum()) > 100
    error = (image - sky(directions)).abs().max(-1).values
    assert float(error[shared].max()) < 0.04
    # looking back, no keyframe has seen anything: black, as without a background
    back = background.image(turned(math.pi), K, WIDTH, HEIGHT)
    assert float(back.abs().max()) == 0.0


def test_an_empty_background_gives_nothing() -> None:
    background = DirectionalBackground()
    assert background.image(turned(0.0), intrinsics(), WIDTH, HEIGHT) is None
    covered = torch.ones(HEIGHT, WIDTH)
    assert background.observe(turned(0.0), intrinsics(), torch.rand(HEIGHT, WIDTH, 3), covered) == 0


def _left_half_map(background: bool) -> tuple[GaussianMap, torch.Tensor]:
    """A map of one keyframe whose surfels cover the left half of its view (stereo found no depth on the right)."""
    gmap = GaussianMap(MapConfig(window=1, iterations=4, background=background))
    pose = camera_pose()
    surfels = voxelized_surfels(pose, 0)
    surfels = surfels.select(surfels.means[:, 0] < -0.1)
    gmap.add_keyframe(0, pose, intrinsics(), view(pose)["image"], surfels, view(pose)["depth"])
    return gmap, pose


def test_a_hole_renders_what_the_keyframe_saw_there_and_stays_a_hole() -> None:
    with_background, pose = _left_half_map(True)
    without, _ = _left_half_map(False)
    image = view(pose)["image"]
    hole = slice(WIDTH // 2 + 8, WIDTH)
    shown = with_background.render(pose, intrinsics(), WIDTH, HEIGHT)
    black = without.render(pose, intrinsics(), WIDTH, HEIGHT)
    assert float(black.rgb[:, hole].max()) == 0.0
    assert psnr(shown.rgb[:, hole], image[:, hole]) > 25
    assert psnr(shown.rgb, image) > psnr(black.rgb, image) + 6
    # coverage and depth stay the surfels' own: the hole is still measured as a hole
    assert torch.equal(shown.alpha, black.alpha) and torch.equal(shown.depth, black.depth)
    assert float(shown.alpha[:, hole].max()) < 0.05
    # a constant background asked for by the caller replaces the map's
    white = with_background.render(pose, intrinsics(), WIDTH, HEIGHT, background=torch.ones(3))
    assert float(white.rgb[:, hole].min()) > 0.95


def test_the_background_travels_with_the_map_state() -> None:
    gmap, pose = _left_half_map(True)
    restored = GaussianMap.from_state_dict(unpack(pack(gmap.state_dict())))
    before = gmap.render(pose, intrinsics(), WIDTH, HEIGHT).rgb
    after = restored.render(pose, intrinsics(), WIDTH, HEIGHT).rgb
    assert torch.allclose(before, after, atol=1e-6)
    assert float(after[:, WIDTH // 2 + 8:].max()) > 0.1


def test_refinement_sees_the_background_behind_the_surfels() -> None:
    """The hole's pixels are explained by the background, so the refinement's loss is far lower with it."""
    with_background, _ = _left_half_map(True)
    without, _ = _left_half_map(False)
    explained = with_background.refine(4).losses
    unexplained = without.refine(4).losses
    assert explained[0] < 0.5 * unexplained[0]


def test_directions_the_map_mostly_covers_are_not_background() -> None:
    """A keyframe's border band (no stereo depth) that later keyframes cover stays out of the background, so the
    refinement still fills it with surfels; the sky, never covered, stays in."""
    background = DirectionalBackground()
    K, pose = intrinsics(), turned(0.0)
    colours = sky(pixel_directions(pose, K, WIDTH, HEIGHT))
    border = torch.ones(HEIGHT, WIDTH)
    border[:, -6:] = 0.0  # the first keyframe's right border band
    background.observe(pose, K, colours, border)
    band = background.image(pose, K, WIDTH, HEIGHT)[:, -3:]
    assert float((band.max(-1).values > 0.1).float().mean()) > 0.9
    covered = torch.ones(HEIGHT, WIDTH)
    background.observe(pose, K, colours, covered)
    background.observe(pose, K, colours, covered)
    assert background.image(pose, K, WIDTH, HEIGHT) is None  # covered twice as often as seen through
    sky_band = torch.ones(HEIGHT, WIDTH)
    sky_band[:8] = 0.0  # the top rows: never covered
    for _ in range(4):  # the top rows were covered three times so far: now seen through more often
        background.observe(pose, K, colours, sky_band)
    image = background.image(pose, K, WIDTH, HEIGHT)
    assert float((image[:6].max(-1).values > 0.1).float().mean()) > 0.9
    assert float(image[12:].max()) == 0.0
