"""Textureless regions completed from their border (worker.depth.border_planes): a plain wall above its skirting
board, or seen only where it meets the floor, takes the wall's plane standing on the floor; edges all around at
one height give a table top; a border far above any dominant plane fills nothing."""

from __future__ import annotations

import cv2
import numpy as np
from scenes import engine_keyframe_depths, looking_down, texture

from worker.depth.border_planes import BorderSettings, border_plane, fill_from_borders
from worker.depth.world_planes import Plane, PlaneSettings, camera_rays, plane_depth

H, W = 120, 160
K = np.array([[144.0, 0, 80.0], [0, 144.0, 60.0], [0, 0, 1.0]])
FLOOR = Plane(np.array([0.0, 0.0, 1.0]), 0.0, 0.5)  # z = 0, world z up
WALL = Plane(np.array([0.0, -1.0, 0.0]), 0.8, 0.0)  # y = 0.8: in front of the camera
SKIRTING_TOP = 0.1  # metres above the floor


def _pose(height: float = 1.0, pitch_deg: float = 30.0) -> np.ndarray:
    """Camera-to-world pose at `height` above the floor, looking along +y (at the wall) and down by `pitch_deg`."""
    return looking_down(height, pitch_deg)


def _room(skirting: float = SKIRTING_TOP, noise: float = 0.004):
    """(image, supported depth, true depth, wall mask, pose): a textured floor and a plain wall; depth is known on
    the floor and on the wall's skirting band (up to `skirting` above the floor), with stereo's noise (`noise` of
    the depth), not on the wall above it."""
    pose = _pose()
    floor = plane_depth(FLOOR, pose, K, (H, W))
    wall = plane_depth(WALL, pose, K, (H, W))
    on_wall = (wall > 0) & ((floor <= 0) | (wall < floor))
    truth = np.where(on_wall, wall, floor)
    ys, xs = np.mgrid[0:H, 0:W]
    centre = pose[:3, 3]
    rays = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    height = centre[2] + (rays @ pose[:3, :3].T)[..., 2] * truth
    band = on_wall & (height <= skirting)
    image = np.full((H, W, 3), 200, np.uint8)  # the plain wall
    image[band] = 245  # the white skirting board, a clear edge against the wall
    checker = ((xs // 6 + ys // 6) % 2).astype(bool)
    image[~on_wall] = np.where(checker[~on_wall, None], 90, 130).astype(np.uint8)  # a patterned carpet
    noisy = truth * (1 + np.random.default_rng(0).normal(0, noise, truth.shape))
    depth = np.where(~on_wall | band, noisy, 0).astype(np.float32)
    return image, depth, truth, on_wall & ~band, pose


def test_a_plain_wall_above_its_skirting_board_takes_the_wall_plane() -> None:
    image, depth, truth, wall, pose = _room()
    assert wall.mean() > 0.2 and (depth[wall] == 0).all()
    filled_depth, filled = fill_from_borders(depth, image, [FLOOR], pose, K)
    assert filled[wall].mean() > 0.95
    error = np.abs(filled_depth[filled] - truth[filled]) / truth[filled]
    assert np.median(error) < 0.02 and np.percentile(error, 95) < 0.05
    assert np.array_equal(filled_depth[depth > 0], depth[depth > 0])  # supported depth is kept
    assert not filled[depth > 0].any()


def test_stray_matches_on_the_plain_wall_take_its_plane() -> None:
    # A few scattered pixels of the wall region with a wrong depth (stereo's chance matches on a textureless
    # surface): the region still counts as unsupported, and those pixels take the plane like its holes.
    image, depth, truth, wall, pose = _room()
    rng = np.random.default_rng(3)
    inside = cv2.erode(wall.astype(np.uint8), np.ones((17, 17), np.uint8)) > 0  # away from the board's edge
    rows, cols = np.nonzero(inside)
    pick = rng.choice(len(rows), int(0.02 * len(rows)), replace=False)
    stray = np.zeros_like(wall)
    stray[rows[pick], cols[pick]] = True
    depth = np.where(stray, 0.7 * truth, depth).astype(np.float32)
    filled_depth, filled = fill_from_borders(depth, image, [FLOOR], pose, K)
    assert filled[stray].all() and np.allclose(filled_depth[stray], truth[stray], rtol=0.02)
    kept = (depth > 0) & ~stray
    assert np.array_equal(filled_depth[kept], depth[kept]) and not filled[kept].any()


def test_a_plain_wall_seen_only_where_it_meets_the_floor_stands_on_the_floor() -> None:
    # Without a skirting band, the wall region's border is floor along the junction: the region, cut off from the
    # floor by an edge and holding no support of its own, is not taken for more floor but for a wall standing there.
    image, depth, truth, wall, pose = _room(skirting=0.0)
    assert not (depth[wall] > 0).any()
    filled_depth, filled = fill_from_borders(depth, image, [FLOOR], pose, K)
    assert filled[wall].mean() > 0.9
    assert np.median(np.abs(filled_depth[filled] - truth[filled]) / truth[filled]) < 0.03


def test_a_line_along_the_floor_is_a_wall_and_edges_all_around_at_one_height_a_table_top() -> None:
    rng = np.random.default_rng(0)
    pose = _pose()
    region_rays = camera_rays(K, (H, W))[:40].reshape(-1, 3) @ pose[:3, :3].T

    def seen(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(noisy points, their depths, their pixels)."""
        cam = (points - pose[:3, 3]) @ pose[:3, :3]
        pixels = cam @ K.T
        return points + rng.normal(0, 0.002, points.shape), cam[:, 2], pixels[:, :2] / pixels[:, 2:]

    # A horizontal line 8 cm above the floor: a horizontal plane through a line is not trusted, a wall standing on
    # the floor is.
    line = np.column_stack([rng.uniform(-0.6, 0.6, 400), np.full(400, 0.8), np.full(400, 0.08)])
    plane = border_plane(*seen(line), [FLOOR], pose[:3, 3], region_rays, W, BorderSettings())
    assert plane is not None and abs(abs(plane.normal[1]) - 1) < 0.02 and abs(abs(plane.offset) - 0.8) < 0.01
    # A table's edges all around, 40 cm above the floor (too high for a wall's junction): the table top.
    t = rng.uniform(0, 4, 400)
    side = np.floor(t).astype(int)
    u = t - side
    x = np.select([side == 0, side == 1, side == 2], [u, np.ones_like(u), 1 - u], np.zeros_like(u)) * 0.6 - 0.3
    y = np.select([side == 0, side == 1, side == 2], [np.zeros_like(u), u, np.ones_like(u)], 1 - u) * 0.4 + 0.7
    table = np.column_stack([x, y, np.full(400, 0.4)])
    plane = border_plane(*seen(table), [FLOOR], pose[:3, 3], region_rays, W, BorderSettings())
    assert plane is not None and abs(abs(plane.normal[2]) - 1) < 1e-9 and abs(abs(plane.offset) - 0.4) < 0.01


def test_a_wall_seen_far_above_the_dominant_plane_is_not_completed() -> None:
    # The only dominant plane lies 3 m below the camera's floor: no junction is seen, so no perpendicular plane is
    # tried (a roof line against the sky), and the band is a line, not the edges of a horizontal surface.
    image, depth, _, wall, pose = _room()
    below = Plane(FLOOR.normal, 3.0, 0.5)
    _, filled = fill_from_borders(depth, image, [below], pose, K)
    assert not filled[wall].any()
    assert fill_from_borders(depth, image, [], pose, K)[1].sum() == 0


def test_the_fill_does_not_reach_past_the_supported_depths() -> None:
    image, depth, _, wall, pose = _room()
    settings = BorderSettings(depth_margin=1.0)
    far = np.percentile(depth[depth > 0], 99)
    filled_depth, filled = fill_from_borders(depth, image, [FLOOR], pose, K, settings)
    assert filled.any() and filled_depth[filled].max() <= far + 1e-6


def _render_room(pose: np.ndarray, carpet: np.ndarray, board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(RGB, true depth) of a carpeted floor and a plain wall with a grained skirting board, seen from `pose`."""
    floor = plane_depth(FLOOR, pose, K, (H, W))
    wall = plane_depth(WALL, pose, K, (H, W))
    on_wall = (wall > 0) & ((floor <= 0) | (wall < floor))
    truth = np.where(on_wall, wall, floor)
    world = camera_rays(K, (H, W)) * truth[..., None] @ pose[:3, :3].T + pose[:3, 3]
    u = ((world[..., 0] + 1.2) * 100).astype(np.float32)
    carpet_grey = cv2.remap(carpet, u, ((world[..., 1] + 0.5) * 100).astype(np.float32), cv2.INTER_LINEAR)
    board_grey = cv2.remap(board, u, (world[..., 2] * 100).astype(np.float32), cv2.INTER_LINEAR)
    grey = np.where(on_wall, np.where(world[..., 2] <= SKIRTING_TOP, 0.75 + 0.2 * board_grey, 0.6),
                    0.1 + 0.5 * carpet_grey)
    return np.repeat((255 * grey).astype(np.uint8)[..., None], 3, axis=-1), truth


def test_the_engine_completes_a_plain_wall_from_its_skirting_board() -> None:
    """Posed RGB keyframe depth as the engine builds it (stereo, propagation, planes): with border planes the
    plain wall, which stereo and the dominant planes leave empty, takes the wall's depth."""
    carpet, board = texture(0), texture(1)
    poses = []
    for i in range(16):
        pose = _pose(height=1.0, pitch_deg=35.0)
        pose[:2, 3] = (0.015 * i, -0.7)  # 1.5 m from the wall, moving along it
        poses.append(pose)
    frames = [_render_room(pose, carpet, board) for pose in poses]

    images = [image for image, _ in frames]
    with_borders = engine_keyframe_depths(images, poses, K, PlaneSettings(), BorderSettings())
    without = engine_keyframe_depths(images, poses, K, PlaneSettings())
    covered, covered_before = [], []
    for (kf, depth), (_, before) in zip(with_borders, without, strict=True):
        image, truth = frames[kf]
        plain = image[..., 0] == int(255 * 0.6)  # the wall above the board
        covered.append((depth[plain] > 0).mean())
        covered_before.append((before[plain] > 0).mean())
        both = plain & (depth > 0)
        if both.any():
            assert np.median(np.abs(depth[both] - truth[both]) / truth[both]) < 0.03
    assert len(covered) == 4 and plain.mean() > 0.3
    assert np.mean(covered_before) < 0.3
    assert np.mean(covered) > 0.8
