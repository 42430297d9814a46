"""How well a sequence's given poses agree with its images: the 3-view reprojection error.

Corners tracked (Lucas-Kanade) from frame i to i+s and i+2s are triangulated from frames i and i+s with the given
poses and projected into frame i+2s; the median distance to where they were tracked, in pixels at the working
size, over triples spread along the sequence, beside the same points' error with frame i+2s's pose fitted to them
(what the images allow) and the ratio of the two: the figure `pose_mode: auto` judges posed RGB sessions by
(`worker.tracking.pose_agreement`, the one implementation). Exact poses leave the tracking noise (a few tenths of a
pixel, ratio about 1); device poses whose steps disagree with the images (scale along the motion, jitter) leave
more, and multi-view stereo and the map built on them inherit it (issue 21 point 1: posed RGB below RGB only on
KITTI and VAMR).

    python -m bench pose_consistency --source DIR [--source DIR ...] [--width 320] [--step 2] [--triples 25]
        [--max-ratio 1.5]
"""

from __future__ import annotations

import argparse

import numpy as np

from worker.tracking.pose_agreement import sequence_errors, verdict
from worker.tracking.seeded_config import PoseChoiceConfig


def reprojection_errors(frames: list, K: np.ndarray, step: int, triples: int) -> list[float]:
    """Median 3-view reprojection error (pixels) of each triple (i, i+step, i+2 step) of `frames` (with poses)."""
    return [e.given_px for e in sequence_errors([f.image for f in frames], [f.pose for f in frames], K, step,
                                                 triples)]


def main(argv: list[str] | None = None) -> int:
    from worker.data import open_source

    parser = argparse.ArgumentParser(prog="python -m bench pose_consistency", description=__doc__.split("\n")[0])
    parser.add_argument("--source", action="append", required=True, help="dataset folder with poses")
    parser.add_argument("--width", type=int, default=320, help="working width (the source's aspect ratio)")
    parser.add_argument("--step", type=int, default=2, help="frames between the views of a triple")
    parser.add_argument("--triples", type=int, default=25)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--max-ratio", type=float, default=PoseChoiceConfig().max_ratio,
                        help="the ratio above which poses disagree (the engine's input.pose_choice.max_ratio)")
    args = parser.parse_args(argv)
    for source in args.source:
        probe = open_source(source, use_gt_poses=True, max_frames=1)
        width, height = probe.intrinsics.width, probe.intrinsics.height
        size = (args.width, round(height * args.width / width))
        src = open_source(source, use_gt_poses=True, max_frames=args.max_frames, resize=size)
        frames = [f for f in src if f.pose is not None]
        K = src.intrinsics.matrix().numpy().astype(np.float64)
        errors = sequence_errors([f.image for f in frames], [f.pose for f in frames], K, args.step, args.triples)
        if not errors:
            print(f"{source}: no triple with parallax")
            continue
        result = verdict(errors, args.max_ratio)
        given = [e.given_px for e in errors]
        print(f"{source}: {size[0]}x{size[1]}, step {args.step}: 3-view reprojection error median "
              f"{result.given_px:.2f} px (p90 {np.percentile(given, 90):.2f}), fitted {result.fitted_px:.2f} px, "
              f"ratio {result.ratio:.2f} over {result.triples} triples: "
              f"{'agree' if result.agree else 'disagree'} (max ratio {args.max_ratio})")
    return 0
