"""Is it the odometry's scale or the reference's speed? RGB-only visual odometry on a sequence with reference poses,
from a chosen start frame: at each of its keyframes, its units per unit of the reference (its distance from the last
keyframe over the reference's) beside the scene's own scale in its units (the median height below the camera of the
map points it sees well below the horizon: the road, for a car). Where the first changes and the second holds, the
odometry kept its scale and the reference's speed differs from what the images show (KITTI 00's first frames:
bench/journal/52-*.md, fifteenth session); where both change together, the odometry's scale drifted.

Usage: python -m bench vo_scale --source DIR [--size 620x188] [--start 0] [--frames 60] [--json F]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "icl_mini"
# points at least this far below the optical axis (y / z in the camera) are the ground's
BELOW_HORIZON = 0.08


def measure(source: str, size: tuple[int, int] | None, start: int, frames: int) -> dict[str, Any]:
    """Per-keyframe scale of the odometry against the reference and against the scene, and the summary figures."""
    from worker.data import open_source
    from worker.eval import absolute_trajectory_error
    from worker.tracking.projection import to_camera
    from worker.tracking.visual_odometry import VisualOdometry

    sequence = list(open_source(source, max_frames=start + frames, resize=size, use_gt_depth=False,
                                use_gt_poses=False))[start:]
    odometry = VisualOdometry()
    reference = np.stack([f.gt_pose for f in sequence])
    poses, rows, seen = [], [], set()
    for n, frame in enumerate(sequence):
        poses.append(odometry.track(frame, frame.intrinsics).pose)
        keyframes = odometry.map.keyframes
        if len(keyframes) < 3 or keyframes[-1].index in seen:
            continue
        kf, previous = keyframes[-1], keyframes[-2]
        seen.add(kf.index)
        a, b = sequence.index(next(f for f in sequence if f.index == previous.index)), n
        metres = float(np.linalg.norm(reference[b, :3, 3] - reference[a, :3, 3]))
        units = float(np.linalg.norm(kf.pose[:3, 3] - previous.pose[:3, 3]))
        points = to_camera(odometry.map.positions[kf.point_ids[kf.point_ids >= 0]], kf.pose)
        ground = points[(points[:, 2] > 0) & (points[:, 1] > BELOW_HORIZON * points[:, 2])]
        rows.append({"frame": int(kf.index), "units_per_reference_unit": units / metres if metres > 0 else None,
                     "ground_points": int(len(ground)),
                     "ground_height_units": float(np.median(ground[:, 1])) if len(ground) >= 5 else None})
    steps = np.linalg.norm(np.diff(np.stack(poses)[:, :3, 3], axis=0), axis=1)
    reference_steps = np.linalg.norm(np.diff(reference[:, :3, 3], axis=0), axis=1)
    ratio = steps / np.maximum(reference_steps, 1e-12)
    moving = ratio[3:7][ratio[3:7] > 0]
    growth = float(np.median(ratio[-20:]) / np.median(moving)) if len(moving) else None
    ate = absolute_trajectory_error(np.stack(poses), reference, "sim3").rmse
    return {"source": source, "start": start, "frames": len(sequence), "keyframes": rows,
            "step_growth": growth, "ate_sim3": float(ate)}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench vo_scale")
    parser.add_argument("--source", default=str(DATA), help="a sequence with reference poses (default: icl_mini)")
    parser.add_argument("--size", default=None, help="WxH (default: the frames' own)")
    parser.add_argument("--start", type=int, default=0, help="the first frame")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--json", default=None, help="write the figures here")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x")) if args.size else None
    result = measure(args.source, size, args.start, args.frames)
    for row in result["keyframes"]:
        scale, height = row["units_per_reference_unit"], row["ground_height_units"]
        print(f"keyframe {row['frame']:5d}  units per reference unit "
              f"{'-' if scale is None else f'{scale:.4f}'}  ground {row['ground_points']:4d} points at "
              f"{'-' if height is None else f'{height:.4f}'} units")
    growth = result["step_growth"]
    print(f"step growth (last 20 frames over frames 3-6): {'-' if growth is None else f'{growth:.3f}'}; "
          f"ATE (sim3) {result['ate_sim3']:.4f}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0
