"""Holes filled from the map's planes (worker.depth.world_planes): planes found in keyframes' confident points, a
uniform floor filled from a small confident patch of it, and, in the engine's keyframe depth, a synthetic room's
textureless floor that stereo and local propagation leave mostly empty."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scenes import engine_keyframe_depths, looking_down

from worker.depth.world_planes import PlaneSettings, fill_from_planes, fit_planes, plane_depth

FLOOR_GREY, BOX_GREY = 120, 40


def _floor_depth(pose: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """True z-depth of the floor z = 0 at each pixel (0 where the ray does not go down), by ray casting."""
    H, W = shape
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1) @ pose[:3, :3].T
    down = -rays[..., 2]
    return np.where(down > 1e-6, pose[2, 3] / np.where(down > 1e-6, down, 1.0), 0.0)


def _floor_view(scale: float = 1.0):
    """A uniform floor seen from 1.5 m (x `scale`) with a dark box standing on it; confident depth only on a patch
    of the floor and on the box's front (off the floor plane)."""
    H, W = 120, 160
    K = np.array([[144.0, 0, 80.0], [0, 144.0, 60.0], [0, 0, 1.0]])
    pose = looking_down(1.5 * scale, 35.0)
    truth = _floor_depth(pose, K, (H, W))
    image = np.full((H, W, 3), FLOOR_GREY, np.uint8)
    image[55:85, 60:100] = BOX_GREY
    depth = np.zeros((H, W), np.float32)
    depth[95:112, 15:50] = truth[95:112, 15:50]  # the floor patch stereo found
    depth[65:78, 68:92] = 0.8 * truth[65:78, 68:92]  # the box's front, nearer than the floor behind it
    return image, depth, truth, pose, K


def _floor_plane(scale: float = 1.0) -> list:
    """The planes the memory finds in floor points and fewer points of a wall (above its skirting), ~3 m away."""
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(-2, 2, 3000), rng.uniform(1, 5, 3000), np.zeros(3000)]) * scale
    wall = np.column_stack([rng.uniform(-2, 2, 1000), np.full(1000, 5.0), rng.uniform(0.1, 2, 1000)]) * scale
    points = np.concatenate([floor, wall])
    return fit_planes(points, np.full(len(points), 3.0 * scale), PlaneSettings())


def test_planes_are_found_in_noisy_points_with_outliers_but_not_in_a_line() -> None:
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(-2, 2, 2000), rng.uniform(1, 5, 2000), rng.normal(0, 0.01, 2000)])
    wall = np.column_stack([rng.normal(3.0, 0.01, 1200), rng.uniform(1, 5, 1200), rng.uniform(0, 2, 1200)])
    clutter = rng.uniform([-2, 1, 0], [3, 5, 2], (600, 3))
    points = np.concatenate([floor, wall, clutter])
    planes = fit_planes(points, np.linalg.norm(points, axis=1), PlaneSettings())
    assert len(planes) == 2
    assert abs(abs(planes[0].normal[2]) - 1) < 1e-3 and abs(planes[0].offset) < 0.01  # the floor, larger first
    assert abs(abs(planes[1].normal[0]) - 1) < 1e-3 and abs(abs(planes[1].offset) - 3.0) < 0.01
    assert planes[0].share > planes[1].share > 0.3
    line = np.column_stack([np.linspace(0, 4, 3000), np.zeros(3000), rng.normal(0, 1e-4, 3000)])
    assert fit_planes(line, np.full(3000, 3.0), PlaneSettings()) == []  # every plane through it fits


def test_a_uniform_floor_is_filled_from_a_patch_and_other_regions_are_left_alone() -> None:
    image, depth, truth, pose, K = _floor_view()
    planes = _floor_plane()
    assert len(planes) == 2 and abs(abs(planes[0].normal[2]) - 1) < 1e-6  # the floor first, then the wall
    out, filled = fill_from_planes(depth, image, planes, pose, K)
    floor = (image[..., 0] == FLOOR_GREY) & (truth > 0)
    box = image[..., 0] == BOX_GREY
    reach = PlaneSettings().depth_margin * np.percentile(depth[depth > 0], 99)  # not out to the horizon
    assert filled[floor & (truth <= reach)].mean() > 0.9 and not filled[truth > reach].any()
    assert filled.sum() > 10 * (depth > 0).sum()  # the floor, far beyond the patch
    assert np.allclose(out[filled], truth[filled], rtol=1e-6)
    assert not filled[box].any()  # bounded by its edges, and its own depth is off the plane
    assert np.array_equal(out[depth > 0], depth[depth > 0]) and not filled[depth > 0].any()
    assert not filled[truth <= 0].any()  # above the horizon the floor is never met
    # without the floor patch nothing in the view lies on the plane: nothing is filled
    alone = np.where(box, depth, 0).astype(np.float32)
    assert not fill_from_planes(alone, image, planes, pose, K)[1].any()


def test_the_fill_is_the_same_at_any_scale() -> None:
    image, depth, _, pose, K = _floor_view()
    image10, depth10, _, pose10, _ = _floor_view(scale=10.0)
    _, filled = fill_from_planes(depth, image, _floor_plane(), pose, K)
    _, filled10 = fill_from_planes(depth10, image10, _floor_plane(10.0), pose10, K)
    assert filled.mean() > 0.4 and np.array_equal(filled, filled10)


def test_plane_depth_is_zero_behind_the_camera_and_at_grazing_angles() -> None:
    _, _, truth, pose, K = _floor_view()
    plane = _floor_plane()[0]
    z = plane_depth(plane, pose, K, truth.shape)
    assert np.allclose(z, truth, rtol=1e-6)
    grazing = plane_depth(plane, pose, K, truth.shape, min_incidence=0.3)
    assert (grazing > 0).sum() < (z > 0).sum() and np.allclose(grazing[grazing > 0], truth[grazing > 0])


def _texture(seed: int = 0, size: int = 256) -> np.ndarray:
    """Smooth random grey levels in [0, 1] (float32 [size, size])."""
    noise = np.random.default_rng(seed).random((size, size)).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 1.5)
    return (blurred - blurred.min()) / np.ptp(blurred)


RUG = (-0.05, 0.55, 0.9, 1.4)  # x0, x1, y0, y1 (metres on the floor)


def _render_floor(pose: np.ndarray, K: np.ndarray, shape: tuple[int, int], texture: np.ndarray) -> np.ndarray:
    """RGB of a uniform grey floor with one textured rug (`RUG`, 1 cm texels), seen from `pose`."""
    truth = _floor_depth(pose, K, shape)
    H, W = shape
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1) * truth[..., None]
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    u, v = ((world[..., 0] + 5) * 100) % 255, ((world[..., 1] + 5) * 100) % 255
    grey = cv2.remap(texture, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR)
    x0, x1, y0, y1 = RUG
    rug = (world[..., 0] > x0) & (world[..., 0] < x1) & (world[..., 1] > y0) & (world[..., 1] < y1) & (truth > 0)
    grey = np.where(rug, 0.15 + 0.7 * grey, 0.6)
    return np.repeat((255 * grey).astype(np.uint8)[..., None], 3, axis=-1)


@pytest.fixture(scope="module")
def floor_with_a_rug():
    """16 frames of a camera 1.5 m above the floor looking down 55 degrees, moving sideways 2 cm a frame."""
    H, W = 120, 160
    K = np.array([[144.0, 0, 80.0], [0, 144.0, 60.0], [0, 0, 1.0]])
    texture = _texture()
    poses = []
    for i in range(16):
        pose = looking_down(1.5, 55.0)
        pose[0, 3] = 0.02 * i
        poses.append(pose)
    frames = [(_render_floor(pose, K, (H, W), texture), _floor_depth(pose, K, (H, W))) for pose in poses]
    return frames, poses, K


def _keyframe_depths(frames, poses, K, planes: PlaneSettings | None) -> list[tuple[int, np.ndarray]]:
    """The surfel depth of every 4th frame as the engine's keyframe depth builds it (posed RGB, propagate)."""
    return engine_keyframe_depths([image for image, _ in frames], poses, K, planes)


def test_the_engine_fills_a_uniform_floor_from_the_plane_of_a_rug_on_it(floor_with_a_rug) -> None:
    frames, poses, K = floor_with_a_rug
    with_planes = _keyframe_depths(frames, poses, K, PlaneSettings())
    without = _keyframe_depths(frames, poses, K, None)
    covered, covered_before = [], []
    for (kf, depth), (_, before) in zip(with_planes, without, strict=True):
        image, truth = frames[kf]
        plain = (image[..., 0] == image[0, 0, 0]) & (truth > 0)  # the uniform floor around the rug
        covered.append((depth[plain] > 0).mean())
        covered_before.append((before[plain] > 0).mean())
        both = plain & (depth > 0)
        assert np.median(np.abs(depth[both] - truth[both]) / truth[both]) < 0.02
    assert len(covered) == 4
    assert np.mean(covered_before) < 0.6  # stereo and local propagation reach a band around the rug
    assert np.mean(covered) > np.mean(covered_before) + 0.25 and np.mean(covered) > 0.85


def test_a_keyframe_its_own_stereo_covers_well_keeps_its_depth(floor_with_a_rug) -> None:
    """Above `max_coverage` of confident multi-view depth the planes fill nothing (textured scenes keep the depth
    of what stands in front of their walls); the same keyframes below it are filled."""
    frames, poses, K = floor_with_a_rug
    without = _keyframe_depths(frames, poses, K, None)
    gated = _keyframe_depths(frames, poses, K, PlaneSettings(max_coverage=0.0))
    for (_, depth), (_, before) in zip(gated, without, strict=True):
        assert np.array_equal(depth, before)
