"""RGB-D odometry alone, ours against Open3D's (`open3d.pipelines.odometry`, hybrid photometric + geometric term,
frame to frame) on the same frames: ATE RMSE (SE(3)-aligned, no loop closure) and milliseconds per frame.

`python -m bench rgbd_odometry [--frames N] [--size WxH] [--threads T] [--source S] [--backends B] [--beside-gil]`
on ICL living room (the full 211 frames when /work/shared has them, else tests/data/icl_mini), or on any sequence with
depth (e.g. the synthetic street, `--source "synthetic://seed=1?frames=120&scene=street&fps=10"`; its ATE is also given
as a share of the path). Open3D is a bench extra (`pip install open3d`; on Debian it needs libusb-1.0-0); without it
the peer row says so.

Ours runs once per kernel backend (`--backends native,reference`: the compiled kernels and their numpy reference,
worker.tracking.dense_alignment), giving wall and tracking-thread CPU milliseconds per frame. `--beside-gil` also runs
each backend with a companion thread that keeps the GIL busy with small numpy operations, as the mapping thread does
inside the system: tracking that holds the GIL in its own hot loops is slowed down most by it.
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from contextlib import contextmanager

import numpy as np

from bench.slam import _source


def _frames(size: tuple[int, int], max_frames: int | None, source: str | None):
    from worker.data import open_source

    stride = 1
    if source is None:
        source, stride = _source(1)
    src = open_source(str(source), stride=stride, max_frames=max_frames, resize=size, use_gt_depth=True,
                      use_gt_poses=False)
    return list(src), src.intrinsics


def run_ours(frames, intrinsics, backend: str = "auto") -> tuple[np.ndarray, float, int, float]:
    """(poses, seconds per frame, frames lost, tracking-thread CPU seconds per frame)."""
    from worker.tracking.rgbd_odometry import RgbdOdometry

    odometry = RgbdOdometry()
    odometry.settings.backend = backend
    poses, lost = [], 0
    start, cpu = time.perf_counter(), time.thread_time()
    for frame in frames:
        result = odometry.track(frame, intrinsics)
        poses.append(result.pose)
        lost += not result.tracked
    n = len(frames)
    return np.stack(poses), (time.perf_counter() - start) / n, lost, (time.thread_time() - cpu) / n


@contextmanager
def gil_companion():
    """A thread that holds the GIL in small numpy operations (like the mapping thread's Python between its kernels)
    while the block runs; yields a counter of its rounds."""
    stop, rounds = threading.Event(), [0]

    def work() -> None:
        a = np.random.default_rng(0).random((32, 32))
        while not stop.is_set():
            for _ in range(100):
                a = np.tanh(a @ a.T * 0.01 + a.mean(0))
            rounds[0] += 1

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    try:
        yield rounds
    finally:
        stop.set()
        thread.join()


def run_open3d(frames, intrinsics) -> tuple[np.ndarray, float, int]:
    """Open3D's frame-to-frame RGB-D odometry chained, seeded by the previous motion like ours."""
    import open3d as o3d

    camera = o3d.camera.PinholeCameraIntrinsic(intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy,
                                               intrinsics.cx - 0.5, intrinsics.cy - 0.5)
    option = o3d.pipelines.odometry.OdometryOption()
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(frame):
        colour = o3d.geometry.Image(np.ascontiguousarray(frame.image))
        depth = o3d.geometry.Image(np.ascontiguousarray(frame.depth.astype(np.float32)))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(colour, depth, depth_scale=1.0,
                                                                  depth_trunc=20.0, convert_rgb_to_intensity=True)

    poses = [np.eye(4)]
    velocity = np.eye(4)
    lost = 0
    start = time.perf_counter()
    previous = rgbd(frames[0])
    for frame in frames[1:]:
        current = rgbd(frame)
        ok, T_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            current, previous, camera, velocity, jacobian, option)  # maps current-frame points into previous
        if not ok:
            lost += 1
            T_prev_cur = velocity
        poses.append(poses[-1] @ T_prev_cur)
        velocity = T_prev_cur
        previous = current
    return np.stack(poses), (time.perf_counter() - start) / len(frames), lost


def main(argv: list[str]) -> int:
    import torch

    from worker.eval import absolute_trajectory_error

    parser = argparse.ArgumentParser(prog="python -m bench rgbd_odometry")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--source", default=None, help="a sequence with depth (default: ICL)")
    parser.add_argument("--backends", default="native,reference", help="dense-alignment kernels to run ours with")
    parser.add_argument("--beside-gil", action="store_true", help="also run ours beside a GIL-holding thread")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    size = tuple(int(v) for v in args.size.split("x"))
    frames, intrinsics = _frames(size, args.frames, args.source)
    gt = np.stack([f.gt_pose for f in frames])
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    print(f"{len(frames)} frames at {size[0]}x{size[1]}, path {path:.2f} m, load {os.getloadavg()[0]:.2f}")
    print("| method | ATE RMSE (cm, SE(3)) | % of path | ms / frame | frames / s | frames lost | CPU ms / frame |")
    print("|---|---:|---:|---:|---:|---:|---:|")

    def row(name: str, poses: np.ndarray, seconds: float, lost: int, cpu: float | None = None) -> None:
        ate = absolute_trajectory_error(poses, gt, "se3").rmse
        cpu_text = "" if cpu is None else f"{1000 * cpu:.1f}"
        print(f"| {name} | {100 * ate:.2f} | {100 * ate / path:.3f} | {1000 * seconds:.1f} | {1 / seconds:.1f} | "
              f"{lost} | {cpu_text} |", flush=True)

    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    run_ours(frames[:3], intrinsics)  # builds (or loads) the compiled kernels outside the timing
    for backend in backends:
        row(f"Flash-Mono RGB-D odometry ({backend})", *run_ours(frames, intrinsics, backend))
    for backend in backends if args.beside_gil else []:
        with gil_companion() as rounds:
            result = run_ours(frames, intrinsics, backend)
        row(f"Flash-Mono RGB-D odometry ({backend}) beside a GIL-holding thread ({rounds[0]} rounds)", *result)
    try:
        row("Open3D RGB-D odometry (hybrid)", *run_open3d(frames, intrinsics))
    except ImportError as err:
        print(f"| Open3D RGB-D odometry (hybrid) | not installed ({err}) | | | | | |")
    print(f"load after: {os.getloadavg()[0]:.2f}")
    return 0
