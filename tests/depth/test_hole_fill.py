"""Hole filling (worker.depth.hole_fill): a textureless patch of a synthetic room's wall, left without depth by
multi-view stereo, takes the wall's depth from the confident pixels around it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from worker.data.synthetic import Material, SyntheticScene, default_intrinsics
from worker.depth import estimate_depth
from worker.depth.hole_fill import fill_depth

WIDTH, HEIGHT = 160, 120
SEED, VIEW, NEIGHBOURS = 10_001, 30, (28, 32, 26, 34)


def _in_patch(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Plain patches on the walls: 1.2 m wide every 2 m, from 0.7 to 2.1 m high (wall coordinates, metres)."""
    return ((u % 2.0) > 0.4) & ((u % 2.0) < 1.6) & (v > 0.7) & (v < 2.1)


@dataclasses.dataclass(frozen=True)
class PlainPatches(Material):
    """The walls' material with textureless (one colour per face) patches."""

    def albedo(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        out = super().albedo(uv, face)
        plain = _in_patch(uv[:, 0], uv[:, 1])
        out[plain] = np.clip(self.color_a * self.face_tint[face[plain]], 0, 1)
        return out


@pytest.fixture(scope="module")
def wall_view():
    scene = SyntheticScene(SEED)
    walls = scene.room_materials["walls"]
    scene.room_materials["walls"] = PlainPatches(**{f.name: getattr(walls, f.name)
                                                    for f in dataclasses.fields(walls)})
    intr = default_intrinsics(WIDTH, HEIGHT)
    poses = scene.camera_path(60, revisit=False)
    image, truth = scene.render(poses[VIEW], intr)
    neighbours = [(scene.render(poses[j], intr)[0], poses[j]) for j in NEIGHBOURS]
    K = intr.matrix().numpy().astype(np.float64)
    estimate = estimate_depth(image, K, poses[VIEW], neighbours)
    # the patch's pixels, from the true geometry: on a wall (x = +-half length or y = +-half width) inside a patch
    xs, ys = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * truth, (ys - K[1, 2]) / K[1, 1] * truth, truth], -1)
    world = cam @ poses[VIEW][:3, :3].T + poses[VIEW][:3, 3]
    hx, hy, _ = scene.layout.box_halves[0]
    on_x, on_y = np.abs(np.abs(world[..., 0]) - hx) < 0.01, np.abs(np.abs(world[..., 1]) - hy) < 0.01
    u = np.where(on_x, world[..., 1] + hy, world[..., 0] + hx)
    patch = (on_x | on_y) & _in_patch(u, world[..., 2])
    return image, truth, estimate.depth, patch


def test_a_textureless_wall_patch_is_filled_with_the_wall_depth(wall_view) -> None:
    image, truth, stereo, patch = wall_view
    assert patch.mean() > 0.2 and (stereo[patch] > 0).mean() < 0.3  # stereo leaves most of the patch empty
    result = fill_depth(stereo, image)
    assert (result.depth[patch] > 0).mean() > 0.8
    assert np.array_equal(result.depth[stereo > 0], stereo[stereo > 0])  # confident pixels are kept as they are
    assert not result.filled[stereo > 0].any() and result.fill_fraction > 0.2
    error = np.abs(result.depth - truth) / truth
    filled_patch = result.filled & patch
    assert np.median(error[filled_patch]) < 0.015 and np.percentile(error[filled_patch], 90) < 0.05


def test_no_fill_across_colours_or_without_support() -> None:
    # two fronto-parallel planes of different colours; only the left one has confident depth
    image = np.zeros((60, 80, 3), np.uint8)
    image[:, :40] = (200, 60, 60)
    image[:, 40:] = (60, 60, 200)
    depth = np.zeros((60, 80), np.float32)
    depth[:, :40] = 2.0
    depth[20:40, 10:30] = 0.0  # a hole inside the left plane
    result = fill_depth(depth, image)
    assert np.allclose(result.depth[20:40, 10:30], 2.0, rtol=1e-4)  # filled with the plane's depth
    assert not result.filled[:, 40:].any()  # the other colour stays empty
    empty = fill_depth(np.zeros((60, 80), np.float32), image)
    assert not empty.filled.any()
    with pytest.raises(ValueError, match="uint8"):
        fill_depth(depth, image.astype(np.float32))
