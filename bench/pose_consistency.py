"""How well a sequence's given poses agree with its images: the 3-view reprojection error.

Corners tracked (Lucas-Kanade) from frame i to i+s and i+2s are triangulated from frames i and i+s with the given
poses and projected into frame i+2s; the median distance to where they were tracked, in pixels at the working
size, over triples spread along the sequence. Exact poses leave the tracking noise (a few tenths of a pixel);
device poses whose steps disagree with the images (scale along the motion, jitter) leave more, and multi-view
stereo and the map built on them inherit it (issue 21 point 1: posed RGB below RGB only on KITTI and VAMR).

    python -m bench pose_consistency --source DIR [--source DIR ...] [--width 320] [--step 2] [--triples 25]
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np


def reprojection_errors(frames: list, K: np.ndarray, step: int, triples: int) -> list[float]:
    """Median 3-view reprojection error (pixels) of each triple (i, i+step, i+2 step) of `frames` (with poses)."""
    errors = []
    last = len(frames) - 2 * step
    for i in np.linspace(0, max(0, last - 1), min(triples, max(1, last))).astype(int):
        grey = [cv2.cvtColor(frames[j].image, cv2.COLOR_RGB2GRAY) for j in (i, i + step, i + 2 * step)]
        corners = cv2.goodFeaturesToTrack(grey[0], 1500, 0.01, 5)
        if corners is None:
            continue
        second, ok1, _ = cv2.calcOpticalFlowPyrLK(grey[0], grey[1], corners, None)
        third, ok2, _ = cv2.calcOpticalFlowPyrLK(grey[0], grey[2], corners, None)
        ok = (ok1.ravel() == 1) & (ok2.ravel() == 1)
        x0, x1, x2 = corners[ok, 0], second[ok, 0], third[ok, 0]
        w2c = [np.linalg.inv(np.asarray(frames[j].pose, np.float64)) for j in (i, i + step, i + 2 * step)]
        points = cv2.triangulatePoints(K @ w2c[0][:3], K @ w2c[1][:3], x0.T.astype(np.float64),
                                       x1.T.astype(np.float64))
        points = points[:3] / points[3]
        depth = (w2c[0][:3, :3] @ points + w2c[0][:3, 3:])[2]
        projected = K @ (w2c[2][:3, :3] @ points + w2c[2][:3, 3:])
        error = np.linalg.norm(projected[:2].T / projected[2][:, None] - x2, axis=1)
        usable = (depth > 0) & (projected[2] > 0) & (np.linalg.norm(x1 - x0, axis=1) > 1.5)  # some parallax
        if usable.sum() >= 20:
            errors.append(float(np.median(error[usable])))
    return errors


def main(argv: list[str] | None = None) -> int:
    from worker.data import open_source

    parser = argparse.ArgumentParser(prog="python -m bench pose_consistency", description=__doc__.split("\n")[0])
    parser.add_argument("--source", action="append", required=True, help="dataset folder with poses")
    parser.add_argument("--width", type=int, default=320, help="working width (the source's aspect ratio)")
    parser.add_argument("--step", type=int, default=2, help="frames between the views of a triple")
    parser.add_argument("--triples", type=int, default=25)
    parser.add_argument("--max-frames", type=int, default=None)
    args = parser.parse_args(argv)
    for source in args.source:
        probe = open_source(source, use_gt_poses=True, max_frames=1)
        width, height = probe.intrinsics.width, probe.intrinsics.height
        size = (args.width, round(height * args.width / width))
        src = open_source(source, use_gt_poses=True, max_frames=args.max_frames, resize=size)
        frames = [f for f in src if f.pose is not None]
        K = src.intrinsics.matrix().numpy().astype(np.float64)
        errors = reprojection_errors(frames, K, args.step, args.triples)
        print(f"{source}: {size[0]}x{size[1]}, step {args.step}: 3-view reprojection error median "
              f"{np.median(errors):.2f} px (p90 {np.percentile(errors, 90):.2f}) over {len(errors)} triples")
    return 0
