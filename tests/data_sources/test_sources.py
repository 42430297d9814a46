"""Frame sources: format detection, parsing, association, options and errors, on tiny fixtures of each layout."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from dataset_writers import translation_pose, write_depth, write_image

from worker.data import DatasetError, open_source
from worker.data.sources import detect_format
from worker.geometry import Intrinsics, project_points, unproject_depth

ICL_MINI = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


# ---- image folder --------------------------------------------------------------------------------------------------
def test_image_folder_natural_order_options_and_intrinsics(tmp_path):
    images = {i: write_image(tmp_path / f"frame{i}.{'png' if i % 2 else 'jpg'}", value=i * 20) for i in range(12)}
    (tmp_path / "notes.txt").write_text("ignored")
    (tmp_path / "intrinsics.json").write_text(json.dumps(dict(fx=30, fy=30, cx=16, cy=12, width=32, height=24)))
    source = open_source(tmp_path, stride=5, resize=(16, 12), fps=10)
    assert detect_format(tmp_path) == "images" and len(source) == 3
    assert source.intrinsics == Intrinsics(15, 15, 8, 6, 16, 12)
    frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.5, 1.0])  # frames 0, 5, 10 at 10 fps
    assert frames[0].image.shape == (12, 16, 3) and frames[0].intrinsics == source.intrinsics
    assert frames[0].depth is None and frames[0].gt_pose is None and frames[0].pose is None
    # frame5 (png, lossless) downscaled by area averaging matches cv2's own result.
    expected = cv2.resize(images[5], (16, 12), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(frames[1].image, expected)


def test_image_folder_without_camera_and_max_frames(tmp_path):
    for i in range(4):
        write_image(tmp_path / f"{i:03d}.png", value=i)
    source = open_source(tmp_path, max_frames=2)
    assert source.intrinsics is None and len(source) == 2 and len(list(source)) == 2


# ---- video ---------------------------------------------------------------------------------------------------------
def write_video(path: Path, count: int, fps: float = 10.0) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (32, 24))
    assert writer.isOpened()
    for i in range(count):
        writer.write(cv2.cvtColor(write_image(path.parent / "tmp.png", value=i * 25), cv2.COLOR_RGB2BGR))
    writer.release()


def test_video_frames_timestamps_and_resize(tmp_path):
    path = tmp_path / "clip.avi"
    write_video(path, 9)
    camera = Intrinsics(40, 40, 16, 12, 32, 24)
    source = open_source(path, stride=2, resize=(64, 48), intrinsics=camera)
    assert detect_format(path) == "video" and len(source) == 5
    assert source.intrinsics == Intrinsics(80, 80, 32, 24, 64, 48)
    frames = list(source)
    assert len(frames) == 5 and frames[0].image.shape == (48, 64, 3)
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8])
    assert frames[2].image[..., 1].mean() == pytest.approx(100, abs=8)  # frame 4 had green = 100 (MJPG is lossy)


def test_corrupt_video_is_a_clear_error(tmp_path):
    path = tmp_path / "broken.mp4"
    path.write_bytes(b"this is not a video" * 10)
    with pytest.raises(DatasetError, match="video"):
        open_source(path)


# ---- TUM RGB-D -----------------------------------------------------------------------------------------------------
@pytest.fixture
def tum_sequence(tmp_path) -> Path:
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    rgb_stamps = [100.00, 100.033, 100.066, 100.10]
    depth_stamps = [100.005, 100.037, 100.20, 100.098]  # frame 2 has no depth within 20 ms
    for i, t in enumerate(rgb_stamps):
        write_image(root / "rgb" / f"{t:.6f}.png", width=64, height=48, value=i)
    for i, t in enumerate(depth_stamps):
        write_depth(root / "depth" / f"{t:.6f}.png", np.full((48, 64), 1.0 + i), 5000.0)
    (root / "rgb.txt").write_text("# color images\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in rgb_stamps))
    (root / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in depth_stamps))
    gt_lines = [f"{100.0 + k * 0.01:.4f} {k * 0.1} 0 0 0 0 0 1\n" for k in range(12)]
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(gt_lines))
    return root


def test_tum_association_depth_scale_and_camera(tum_sequence):
    source = open_source(tum_sequence, use_gt_poses=True)
    assert detect_format(tum_sequence) == "tum"
    assert source.intrinsics == Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480).scaled(64, 48)
    frames = list(source)
    assert [round(f.timestamp, 3) for f in frames] == [100.0, 100.033, 100.1]
    assert [float(f.depth[0, 0]) for f in frames] == pytest.approx([1.0, 2.0, 4.0])
    # Nearest ground truth: 100.033 -> 100.03 (x = 0.3), 100.10 -> x = 1.0.
    assert [f.gt_pose[0, 3] for f in frames] == pytest.approx([0.0, 0.3, 1.0])
    np.testing.assert_array_equal(frames[1].pose, frames[1].gt_pose)


def test_tum_without_depth_keeps_every_frame(tum_sequence):
    frames = list(open_source(tum_sequence, use_gt_depth=False))
    assert len(frames) == 4 and all(f.depth is None and f.pose is None for f in frames)


def test_tum_malformed_groundtruth(tum_sequence):
    (tum_sequence / "groundtruth.txt").write_text("100.0 1 2 3\n")
    with pytest.raises(DatasetError, match="groundtruth.txt:1: expected 8 numbers"):
        open_source(tum_sequence)


# ---- ICL / Open3D --------------------------------------------------------------------------------------------------
def test_icl_mini_fixture_reads_with_poses_depth_and_scaling():
    source = open_source(ICL_MINI, stride=10, resize=(160, 120))
    assert detect_format(ICL_MINI) == "icl" and len(source) == 8
    assert source.intrinsics == Intrinsics(131.25, 131.25, 79.875, 59.875, 160, 120)
    frames = list(source)
    first = frames[0]
    assert first.depth.shape == (120, 160) and first.depth.dtype == np.float32
    assert 0.5 < float(np.median(first.depth[first.depth > 0])) < 5.0  # metres, not millimetres
    np.testing.assert_allclose(first.gt_pose, np.eye(4), atol=1e-7)
    assert frames[1].timestamp == pytest.approx(1.0)  # 11th line of groundtruth.txt: original frame 30 at 30 fps


def test_icl_open3d_log_layout(tmp_path):
    root = tmp_path / "icl"
    poses = [translation_pose(0.1 * i, 0.2, 0.0) for i in range(3)]
    for i in range(3):
        write_image(root / "image" / f"{i:05d}.jpg", value=i)
        write_depth(root / "depth" / f"{i:05d}.png", np.full((24, 32), 2.0), 1000.0)
    (root / "intrinsics.json").write_text(json.dumps(dict(fx=30, fy=30, cx=16, cy=12, width=32, height=24,
                                                         depth_scale=1000.0, fps=15)))
    blocks = [f"{i} {i} {i + 1}\n" + "\n".join(" ".join(f"{v:.6f}" for v in row) for row in p) + "\n"
              for i, p in enumerate(poses)]
    (root / "trajectory.log").write_text("".join(blocks))
    frames = list(open_source(root))
    assert [f.timestamp for f in frames] == pytest.approx([0, 1 / 15, 2 / 15])
    assert frames[2].gt_pose[0, 3] == pytest.approx(0.2) and frames[2].depth[5, 5] == pytest.approx(2.0)
    (root / "trajectory.log").write_text("".join(blocks[:2]))
    with pytest.raises(DatasetError, match="3 images but 2 poses"):
        open_source(root)


# ---- Replica (NICE-SLAM layout) ------------------------------------------------------------------------------------
def test_replica_layout(tmp_path):
    root = tmp_path / "Replica" / "room0"
    for i in range(3):
        write_image(root / "results" / f"frame{i:06d}.jpg", width=40, height=20, value=i)
        write_depth(root / "results" / f"depth{i:06d}.png", np.full((20, 40), 1.5), 6553.5)
    (root / "traj.txt").write_text("".join(" ".join(str(v) for v in translation_pose(i, 0, 1).ravel()) + "\n"
                                           for i in range(3)))
    (root.parent / "cam_params.json").write_text(json.dumps(
        {"camera": dict(w=40, h=20, fx=20.0, fy=20.0, cx=19.5, cy=9.5, scale=6553.5)}))
    source = open_source(root, max_frames=2)
    assert detect_format(root) == "replica" and len(source) == 2
    assert source.intrinsics == Intrinsics(20, 20, 19.5, 9.5, 40, 20)
    frames = list(source)
    assert frames[1].gt_pose[0, 3] == 1.0 and frames[1].gt_pose[2, 3] == 1.0
    assert frames[0].depth[3, 3] == pytest.approx(1.5, abs=1e-4)


# ---- ScanNet export ------------------------------------------------------------------------------------------------
def test_scannet_export_uses_depth_resolution_and_skips_invalid_poses(tmp_path):
    root = tmp_path / "scene0054_00"
    (root / "pose").mkdir(parents=True)
    for i in range(3):
        write_image(root / "color" / f"{i}.jpg", width=64, height=48, value=i)
        write_depth(root / "depth" / f"{i}.png", np.full((24, 32), 0.75), 1000.0)
        pose = translation_pose(i) if i != 1 else np.full((4, 4), -np.inf)
        np.savetxt(root / "pose" / f"{i}.txt", pose)
    (root / "intrinsic").mkdir()
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", np.array([[58, 0, 32, 0], [0, 58, 24, 0],
                                                                     [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", np.array([[29, 0, 16, 0], [0, 29, 12, 0],
                                                                     [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    source = open_source(root)
    assert detect_format(root) == "scannet"
    assert source.intrinsics == Intrinsics(29, 29, 16, 12, 32, 24)
    frames = list(source)
    assert frames[0].image.shape == (24, 32, 3) and frames[0].depth[0, 0] == pytest.approx(0.75)
    assert frames[1].gt_pose is None and frames[2].gt_pose[0, 3] == 2.0
    rgb_only = open_source(root, use_gt_depth=False)
    assert rgb_only.intrinsics == Intrinsics(58, 58, 32, 24, 64, 48)
    assert next(iter(rgb_only)).image.shape == (48, 64, 3)


# ---- KITTI odometry ------------------------------------------------------------------------------------------------
def test_kitti_odometry_calibration_times_and_camera_offset(tmp_path):
    root = tmp_path / "dataset" / "sequences" / "05"
    for i in range(3):
        write_image(root / "image_2" / f"{i:06d}.png", width=62, height=19, value=i)
    fx, cx, cy = 7.0, 30.0, 9.0
    p0 = [fx, 0, cx, 0, 0, fx, cy, 0, 0, 0, 1, 0]
    p2 = [fx, 0, cx, fx * 0.06, 0, fx, cy, 0, 0, 0, 1, 0]  # colour camera 6 cm left of cam0: b = +0.06
    (root / "calib.txt").write_text("".join(f"P{k}: " + " ".join(map(str, p)) + "\n"
                                            for k, p in ((0, p0), (1, p0), (2, p2), (3, p2))))
    (root / "times.txt").write_text("0.0\n0.1\n0.2\n")
    poses_dir = tmp_path / "dataset" / "poses"
    poses_dir.mkdir(parents=True)
    (poses_dir / "05.txt").write_text("".join(" ".join(str(v) for v in translation_pose(0, 0, i)[:3].ravel()) + "\n"
                                              for i in range(3)))
    source = open_source(root, use_gt_poses=True)
    assert detect_format(root) == "kitti"
    assert source.intrinsics == Intrinsics(fx, fx, cx, cy, 62, 19)
    frames = list(source)
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.1, 0.2])
    np.testing.assert_allclose(frames[2].gt_pose[:3, 3], [-0.06, 0.0, 2.0])
    assert frames[0].depth is None


# ---- detection and errors ------------------------------------------------------------------------------------------
def test_unknown_and_missing_inputs(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        open_source(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="cannot tell the format"):
        open_source(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="not a video"):
        open_source(tmp_path / "notes.txt")
    with pytest.raises(DatasetError, match="unknown format"):
        open_source(tmp_path, format="colmap")


@pytest.mark.parametrize("options, message", [
    (dict(stride=0), "stride"), (dict(max_frames=0), "max_frames"), (dict(resize=(10, -1)), "resize"),
    (dict(resize=(10,)), "resize"), (dict(fps_typo=3), "bad option"),
])
def test_bad_options(tmp_path, options, message):
    write_image(tmp_path / "0.png")
    with pytest.raises(DatasetError, match=message):
        open_source(tmp_path, **options)


def test_corrupt_image_and_missing_depth_files(tmp_path):
    write_image(tmp_path / "0.png")
    (tmp_path / "1.png").write_bytes(b"\x89PNG garbage")
    frames = iter(open_source(tmp_path))
    next(frames)
    with pytest.raises(DatasetError, match="cannot decode image"):
        next(frames)
    root = tmp_path / "replica"
    write_image(root / "results" / "frame000000.jpg")
    write_image(root / "results" / "frame000001.jpg")
    write_depth(root / "results" / "depth000000.png", np.ones((24, 32)), 6553.5)
    (root / "results" / "depth000001.png").write_bytes(b"not a png")
    (root / "traj.txt").write_text(" ".join(["1"] * 16) + "\n" + " ".join(["1"] * 16) + "\n")
    frames = iter(open_source(root))
    next(frames)
    with pytest.raises(DatasetError, match="cannot decode depth"):
        next(frames)


def photometric_warp_error(source_frame, target_frame, source_pose, target_pose) -> float:
    """Mean |RGB| difference after moving source pixels (with their depth) into the target view."""
    K = source_frame.intrinsics.matrix(torch.float64)
    points = unproject_depth(torch.from_numpy(source_frame.depth.astype(np.float64)), K).reshape(-1, 3).numpy()
    world = points @ source_pose[:3, :3].T + source_pose[:3, 3]
    w2c = np.linalg.inv(target_pose)
    uv, z = project_points(torch.from_numpy(world @ w2c[:3, :3].T + w2c[:3, 3]), K)
    cols, rows = np.floor(uv[:, 0].numpy()).astype(int), np.floor(uv[:, 1].numpy()).astype(int)
    keep = ((source_frame.depth.reshape(-1) > 0) & (z.numpy() > 0) & (cols >= 0) & (cols < source_frame.width)
            & (rows >= 0) & (rows < source_frame.height))
    a = source_frame.image.reshape(-1, 3)[keep] / 255.0
    return float(np.abs(a - target_frame.image[rows[keep], cols[keep]] / 255.0).mean())


def test_icl_poses_depth_and_camera_agree_on_real_frames():
    """Real data: the conventions (c2w, pixel centres, depth units, intrinsics) make frames warp onto each other."""
    frames = list(open_source(ICL_MINI, max_frames=3))
    with_gt = photometric_warp_error(frames[0], frames[2], frames[0].gt_pose, frames[2].gt_pose)
    without = photometric_warp_error(frames[0], frames[2], np.eye(4), np.eye(4))
    assert with_gt < 0.025 and without > 2.5 * with_gt
