"""Multi-view depth benchmark (worker/depth): ICL living room with ground-truth poses, a synthetic sparse-photo case,
and OpenCV's StereoSGBM on a rectified pair as the peer.

ICL: 211 frames at 320x240 (K scaled by 0.5); every 6th frame is a keyframe whose neighbours `select_neighbours`
picks among all the other frames; the depth range and scene depth come from 200 random pixels' depth, standing in
for the tracked map points a SLAM run has. Per keyframe: depth L1 on the pixels marked confident (that have
ground-truth depth), coverage (confident / pixels with ground-truth depth) and wall time per call (after one warm-up
call that compiles the kernels). Targets: L1 <= 5 cm, coverage >= 70 %, <= 150 ms on 2 cores.
Sparse photos: a held-out synthetic room; each reference photo gets four neighbours orbiting the point it looks at
by 20-30 degrees (left, right, up, down). SGBM: the keyframe and its chosen neighbour with the most sideways
baseline, rectified (cv2.stereoRectify + remap), StereoSGBM, the disparities back-projected into the keyframe.

Usage: python -m bench mvs [-- --every 6 --threads 1 --data PATH --seed 10003 --photos 6 --no-range --no-sgbm]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from bench.render import machine

DATA = Path("/work/shared/data/icl_livingroom1_micro")


def _K(intrinsics) -> np.ndarray:
    return np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]])


def _range_from_points(depth: np.ndarray, rng: np.random.Generator, count: int = 200) -> tuple[tuple, float]:
    """(near, far) and the median depth of `count` random valid pixels: what tracked map points would give."""
    valid = depth[depth > 0]
    sample = valid[rng.integers(0, valid.size, count)]
    return (float(np.percentile(sample, 2)) * 0.8, float(np.percentile(sample, 98)) * 1.25), float(np.median(sample))


def _score(depth: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """(L1 on confident pixels with ground truth, coverage of the pixels with ground truth)."""
    valid = gt > 0
    both = valid & (depth > 0)
    l1 = float(np.abs(depth[both] - gt[both]).mean()) if both.any() else float("nan")
    return l1, float(both.sum() / max(valid.sum(), 1))


def _summary(name: str, rows: list[dict]) -> str:
    l1 = [r["l1"] for r in rows if np.isfinite(r["l1"])]
    cov = [r["coverage"] for r in rows]
    ms = [r["ms"] for r in rows]
    met = sum(r["l1"] <= 0.05 and r["coverage"] >= 0.7 for r in rows)
    cpu = f", CPU median {statistics.median(r['cpu_ms'] for r in rows):6.1f} ms" if "cpu_ms" in rows[0] else ""
    return (f"{name:<22} keyframes {len(rows):>3}  L1 mean {100 * statistics.mean(l1):5.2f} cm (worst "
            f"{100 * max(l1):5.2f})  coverage mean {100 * statistics.mean(cov):5.1f} % (lowest {100 * min(cov):5.1f})"
            f"  time median {statistics.median(ms):6.1f} ms (p90 {np.percentile(ms, 90):6.1f}, max {max(ms):6.1f}"
            f"{cpu})  keyframes meeting both targets {met}/{len(rows)}")


def sgbm_depth(ref_image: np.ndarray, ref_pose: np.ndarray, image: np.ndarray, pose: np.ndarray, K: np.ndarray,
               depth_range: tuple[float, float]) -> np.ndarray:
    """StereoSGBM on the rectified pair, depth back in the reference camera (0 where none), float32 [H, W]."""
    H, W = ref_image.shape[:2]
    K_cv = K.copy()
    K_cv[0, 2] -= 0.5  # OpenCV puts pixel centres at integer coordinates
    K_cv[1, 2] -= 0.5
    rel = np.linalg.inv(pose) @ ref_pose  # reference camera -> other camera
    R, T = rel[:3, :3], rel[:3, 3]
    no_distortion = np.zeros(5)
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(K_cv, no_distortion, K_cv, no_distortion, (W, H), R,
                                                T.reshape(3, 1), alpha=0)
    maps = [cv2.initUndistortRectifyMap(K_cv, no_distortion, Ri, Pi, (W, H), cv2.CV_32FC1)
            for Ri, Pi in ((R1, P1), (R2, P2))]
    left, right = (cv2.remap(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), mx, my, cv2.INTER_LINEAR)
                   for img, (mx, my) in zip((ref_image, image), maps, strict=True))
    vertical = abs(P2[1, 3]) > abs(P2[0, 3])  # rectified to vertical epipolar lines: transpose to horizontal
    shift = P2[1, 3] if vertical else P2[0, 3]
    f_rect, baseline = P1[0, 0], abs(shift / P2[0, 0])
    if vertical:
        left, right = cv2.transpose(left), cv2.transpose(right)
    if shift > 0:  # the other camera is on the left (above): mirror both so that disparities are positive
        left, right = cv2.flip(left, 1), cv2.flip(right, 1)
    d_min, d_max = f_rect * baseline / depth_range[1], f_rect * baseline / depth_range[0]
    block = 5
    width = left.shape[1]
    # SGBM needs minDisparity + numDisparities < width - block / 2: very near points beyond that are lost
    num = min(int(np.ceil((d_max - int(d_min)) / 16.0) * 16), (width - block - int(d_min)) // 16 * 16)
    if num < 16:
        return np.zeros((H, W), np.float32)
    matcher = cv2.StereoSGBM.create(minDisparity=int(d_min), numDisparities=num, blockSize=block,
                                    P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                    uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                    mode=cv2.STEREO_SGBM_MODE_SGBM)
    disparity = matcher.compute(left, right).astype(np.float32) / 16.0
    if shift > 0:
        disparity = cv2.flip(disparity, 1)
    if vertical:
        disparity = cv2.transpose(disparity)
    ok = (disparity >= int(d_min)) & (disparity > 0)  # SGBM marks failures with minDisparity - 1
    ys, xs = np.nonzero(ok)
    z = f_rect * baseline / disparity[ok]
    rect = np.stack([(xs - P1[0, 2]) / f_rect * z, (ys - P1[1, 2]) / P1[1, 1] * z, z], axis=1)
    cam = rect @ R1  # rectified -> reference camera (R1 maps reference to rectified)
    cam = cam[np.isfinite(cam).all(axis=1) & (cam[:, 2] > 1e-6)]
    u = np.round(K_cv[0, 0] * cam[:, 0] / cam[:, 2] + K_cv[0, 2]).astype(int)
    v = np.round(K_cv[1, 1] * cam[:, 1] / cam[:, 2] + K_cv[1, 2]).astype(int)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    depth = np.full((H, W), np.inf, np.float32)
    np.minimum.at(depth, (v[inside], u[inside]), cam[inside, 2].astype(np.float32))  # nearest surface wins
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def _sideways(ref_pose: np.ndarray, poses: list[np.ndarray]) -> int:
    """Index of the pose with the longest baseline across the reference camera's optical axis (rectification
    degenerates for motion along it)."""
    return int(np.argmax([np.linalg.norm((ref_pose[:3, :3].T @ (p[:3, 3] - ref_pose[:3, 3]))[:2]) for p in poses]))


def bench_icl(args, config) -> list[str]:
    from worker.data import open_source
    from worker.depth import estimate_depth, select_neighbours

    frames = list(open_source(args.data, resize=(320, 240), use_gt_depth=True, use_gt_poses=True))
    K = _K(frames[0].intrinsics)
    rng = np.random.default_rng(0)
    keyframes = list(range(0, len(frames), args.every))
    print(f"ICL: {len(frames)} frames at 320x240 from {args.data}, {len(keyframes)} keyframes (every {args.every}th)")
    rows, peer = [], []
    for n, k in enumerate(keyframes):
        frame = frames[k]
        depth_range, scene_depth = _range_from_points(frame.depth, rng)
        others = [i for i in range(len(frames)) if i != k]
        chosen = select_neighbours(frame.pose, [frames[i].pose for i in others], config, scene_depth)
        if args.no_range:  # the swept range from the poses alone (neighbours still chosen with the scene depth)
            depth_range = None
        neighbours = [(frames[others[i]].image, frames[others[i]].pose) for i in chosen]
        if n == 0:  # warm-up: compiles (or loads) the kernels and sizes the buffers
            estimate_depth(frame.image, K, frame.pose, neighbours, depth_range, config)
        start, cpu = time.perf_counter(), time.process_time()
        est = estimate_depth(frame.image, K, frame.pose, neighbours, depth_range, config)
        ms, cpu_ms = 1000 * (time.perf_counter() - start), 1000 * (time.process_time() - cpu)
        l1, coverage = _score(est.depth, frame.depth)
        rows.append({"l1": l1, "coverage": coverage, "ms": ms, "cpu_ms": cpu_ms})
        line = (f"  kf {k:>3} views {[others[i] for i in chosen]} L1 {100 * l1:5.2f} cm cov {100 * coverage:5.1f} % "
                f"{ms:6.1f} ms (CPU {cpu_ms:5.1f} ms, {est.backend})")
        if not args.no_sgbm and neighbours:
            j = _sideways(frame.pose, [p for _, p in neighbours])
            start = time.perf_counter()
            sgbm = sgbm_depth(frame.image, frame.pose, neighbours[j][0], neighbours[j][1], K,
                              depth_range or est.depth_range)
            sgbm_ms = 1000 * (time.perf_counter() - start)
            s_l1, s_cov = _score(sgbm, frame.depth)
            peer.append({"l1": s_l1, "coverage": s_cov, "ms": sgbm_ms})
            line += (f" | SGBM with {others[chosen[j]]}: L1 {100 * s_l1:5.2f} cm cov {100 * s_cov:5.1f} % "
                     f"{sgbm_ms:5.1f} ms")
        print(line, flush=True)
    lines = [_summary("ICL plane sweep", rows)]
    if peer:
        lines.append(_summary("ICL StereoSGBM pair", peer))
    return lines


def _orbit(ref_pose: np.ndarray, target: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """The reference camera moved around `target` by yaw (about world z) and pitch (about its own x axis), still
    looking at the target."""
    from worker.data.synthetic import look_at_c2w

    offset = ref_pose[:3, 3] - target
    cy, sy = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    offset = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ offset
    axis = np.cross(offset, [0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    a = np.radians(pitch)
    offset = (offset * np.cos(a) + np.cross(axis, offset) * np.sin(a) + axis * (axis @ offset) * (1 - np.cos(a)))
    position = target + offset
    return look_at_c2w(position, target - position)


def bench_photos(args, config) -> list[str]:
    from worker.data.synthetic import SyntheticScene, default_intrinsics
    from worker.depth import estimate_depth

    scene = SyntheticScene(args.seed)
    intr = default_intrinsics(320, 240)
    K = _K(intr)
    path = scene.camera_path(args.photos, revisit=False)
    rng = np.random.default_rng(1)
    rows = []
    photos = config.model_copy(update={"max_parallax": 1.0})
    print(f"sparse photos: synthetic held-out seed {args.seed}, {args.photos} reference photos, 4 neighbours each "
          "orbiting the looked-at point by 20-30 degrees")
    for n, ref_pose in enumerate(path):
        image, gt = scene.render(ref_pose, intr)
        depth_range, scene_depth = _range_from_points(gt, rng)
        target = ref_pose[:3, 3] + ref_pose[:3, 2] * scene_depth
        moves = [(-rng.uniform(20, 30), 0), (rng.uniform(20, 30), 0), (0, rng.uniform(20, 30)),
                 (0, -rng.uniform(20, 30))]
        neighbours = []
        for yaw, pitch in moves:
            pose = _orbit(ref_pose, target, yaw, pitch)
            neighbours.append((scene.render(pose, intr)[0], pose))
        if n == 0:
            estimate_depth(image, K, ref_pose, neighbours, depth_range, photos)
        start, cpu = time.perf_counter(), time.process_time()
        est = estimate_depth(image, K, ref_pose, neighbours, depth_range, photos)
        ms, cpu_ms = 1000 * (time.perf_counter() - start), 1000 * (time.process_time() - cpu)
        l1, coverage = _score(est.depth, gt)
        rows.append({"l1": l1, "coverage": coverage, "ms": ms, "cpu_ms": cpu_ms})
        print(f"  photo {n}: depth {scene_depth:.2f} m, L1 {100 * l1:5.2f} cm cov {100 * coverage:5.1f} % {ms:6.1f} ms")
    return [_summary("sparse photos (20-30°)", rows)]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench mvs", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="ICL living room folder (Open3D/ICL format)")
    parser.add_argument("--every", type=int, default=6, help="every n-th frame is a keyframe")
    parser.add_argument("--threads", type=int, default=None, help="kernel threads (default: the config's)")
    parser.add_argument("--views", type=int, default=None, help="neighbours per keyframe (config default)")
    parser.add_argument("--seed", type=int, default=10003, help="held-out synthetic scene for the sparse photos")
    parser.add_argument("--photos", type=int, default=6)
    parser.add_argument("--no-sgbm", action="store_true")
    parser.add_argument("--no-photos", action="store_true")
    parser.add_argument("--no-range", action="store_true",
                        help="ICL with the swept depth range from the poses alone (multiples of the baseline)")
    args = parser.parse_args(argv)

    from worker.depth import MultiViewDepthConfig, mvs_cpu

    overrides = {"threads": args.threads, "num_views": args.views}
    config = MultiViewDepthConfig(**{k: v for k, v in overrides.items() if v is not None})
    print(f"machine: {machine()}; compiled kernels: {mvs_cpu.available()}; cv2.setNumThreads({config.threads})")
    cv2.setNumThreads(config.threads)
    print(f"config: {config.model_dump()}")
    lines = []
    if args.data.exists():
        lines += bench_icl(args, config)
    else:
        print(f"ICL data not found at {args.data}: skipped")
    if not args.no_photos:
        lines += bench_photos(args, config)
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")
    for line in lines:
        print(line)
    return 0
