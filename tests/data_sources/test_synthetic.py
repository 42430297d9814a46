"""The synthetic scene generator: determinism, exact geometry (multi-view consistency), loops, URIs, seed split."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from worker.data import DatasetError, open_source
from worker.data.synthetic import (
    HELD_OUT_SEED_START,
    SyntheticScene,
    default_intrinsics,
    is_held_out_seed,
    look_at_c2w,
    make_sequence,
    parse_synthetic_uri,
)
from worker.geometry import project_points, unproject_depth


def test_same_seed_same_frames_different_seed_different_scene():
    a = make_sequence(5, num_frames=4, width=40, height=30)
    b = make_sequence(5, num_frames=4, width=40, height=30)
    c = make_sequence(6, num_frames=4, width=40, height=30)
    fa, fb, fc = a.frame(2), b.frame(2), c.frame(2)
    np.testing.assert_array_equal(fa.image, fb.image)
    np.testing.assert_array_equal(fa.depth, fb.depth)
    np.testing.assert_array_equal(fa.gt_pose, fb.gt_pose)
    assert not np.array_equal(fa.image, fc.image)


def test_frames_carry_exact_camera_depth_and_pose():
    seq = make_sequence(10_001, num_frames=10, width=64, height=48)
    frames = list(seq)
    assert len(seq) == 10 and len(frames) == 10
    f = frames[3]
    assert f.image.dtype == np.uint8 and f.image.shape == (48, 64, 3)
    assert f.depth.dtype == np.float32 and np.all(f.depth > 0.05) and np.all(np.isfinite(f.depth))
    assert f.intrinsics == default_intrinsics(64, 48) and f.timestamp == pytest.approx(0.1)
    R = f.gt_pose[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert f.pose is None  # posed mode only on request
    assert make_sequence(10_001, 2, 16, 12, use_gt_poses=True).frame(1).pose is not None
    assert make_sequence(10_001, 2, 16, 12, use_gt_depth=False).frame(1).depth is None
    assert len(np.unique(f.image.reshape(-1, 3), axis=0)) > 50  # textured, not flat


def test_depth_points_reproject_consistently_into_another_view():
    """World points from frame i's depth land in frame j at j's depth, with the same colour (exact geometry)."""
    seq = make_sequence(10_002, num_frames=120, width=80, height=60)
    fi, fj = seq.frame(10), seq.frame(12)
    K = fi.intrinsics.matrix(torch.float64)
    points_i = unproject_depth(torch.from_numpy(fi.depth.astype(np.float64)), K).reshape(-1, 3).numpy()
    world = points_i @ fi.gt_pose[:3, :3].T + fi.gt_pose[:3, 3]
    w2c_j = np.linalg.inv(fj.gt_pose)
    points_j = world @ w2c_j[:3, :3].T + w2c_j[:3, 3]
    uv, z = project_points(torch.from_numpy(points_j), K)
    uv, z = uv.numpy(), z.numpy()
    cols, rows = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (z > 0) & (cols >= 0) & (cols < 80) & (rows >= 0) & (rows < 60)
    assert inside.mean() > 0.5
    depth_j = fj.depth[rows[inside], cols[inside]]
    # Pixel quantisation moves the landing point by < 1 px; most points must agree to within a few cm.
    close = np.abs(depth_j - z[inside]) < 0.03 * z[inside]
    assert close.mean() > 0.95
    colours_i = fi.image.reshape(-1, 3)[inside][close].astype(float)
    colours_j = fj.image[rows[inside], cols[inside]][close].astype(float)
    assert np.median(np.abs(colours_i - colours_j)) < 12  # Lambertian: a point keeps its colour across views


def test_render_of_a_known_wall_distance():
    scene = SyntheticScene(42)
    half_length = scene.layout.box_halves[0][0]
    # Stand at the room centre at 1.2 m height looking along -x at the end wall (x = -half_length).
    pose = look_at_c2w(np.array([0.0, 0.0, 1.2]), np.array([-1.0, 0.0, 0.0]))
    rgb, depth = scene.render(pose, default_intrinsics(32, 24))
    centre = depth[11:13, 15:17]
    # Unless furniture is in the way, the centre pixel sees the wall exactly half a room length away.
    assert np.all(centre <= half_length + 1e-4)
    assert rgb.shape == (24, 32, 3)


def test_revisit_paths_return_to_the_start_and_others_do_not():
    loop = make_sequence(11, num_frames=50, width=16, height=12, revisit=True).poses
    open_path = make_sequence(11, num_frames=50, width=16, height=12, revisit=False).poses
    step = np.median(np.linalg.norm(np.diff(loop[:, :3, 3], axis=0), axis=1))
    # The last frames of a revisiting path pass within a few steps of the first frame.
    closest = np.min(np.linalg.norm(loop[35:, :3, 3] - loop[0, :3, 3], axis=1))
    assert closest < 3 * step
    assert np.min(np.linalg.norm(open_path[35:, :3, 3] - open_path[0, :3, 3], axis=1)) > 10 * step


def test_camera_stays_clear_of_furniture():
    for seed in (0, 1, 10_000):
        seq = make_sequence(seed, num_frames=30, width=24, height=18)
        for index in range(0, 30, 5):
            assert seq.frame(index).depth.min() > 0.2


def test_uri_options_and_errors():
    source = open_source("synthetic://seed=3?frames=12&width=32&height=24", stride=3, resize=(16, 12))
    assert len(source) == 4 and source.name == "synthetic-3"
    frames = list(source)
    assert frames[1].image.shape == (12, 16, 3) and frames[1].timestamp == pytest.approx(0.1)
    assert frames[1].intrinsics == default_intrinsics(32, 24).scaled(16, 12)
    assert parse_synthetic_uri("synthetic://seed=7?revisit=0&fps=15") == {"seed": 7, "revisit": False, "fps": 15.0}
    for bad in ("synthetic://frames=3", "synthetic://seed=x", "synthetic://seed=1?colour=red"):
        with pytest.raises(DatasetError):
            open_source(bad)
    with pytest.raises(ValueError):
        SyntheticScene(-1)


def test_held_out_seed_split():
    assert HELD_OUT_SEED_START == 10_000
    assert not is_held_out_seed(9_999) and is_held_out_seed(10_000)


def test_frustum_culling_does_not_change_a_single_bit(monkeypatch):
    seq = make_sequence(10_004, num_frames=12, width=40, height=30)
    culled = [seq.scene.render(pose, seq.intrinsics) for pose in seq.poses]
    everything = np.ones(len(seq.scene._bounding_spheres()[1]), bool)
    monkeypatch.setattr(seq.scene, "_in_frustum", lambda pose, intrinsics: everything)
    for pose, (rgb, depth) in zip(seq.poses, culled):
        full_rgb, full_depth = seq.scene.render(pose, seq.intrinsics)
        np.testing.assert_array_equal(rgb, full_rgb)
        np.testing.assert_array_equal(depth, full_depth)
