"""Device poses as measurements (issue 21) on ICL: the same frames with the poses ignored, used as they are
(`pose_mode` prior) or seeding the session's own odometry (`seeded`), with the true poses and with realistic device
poses (the true poses with injected odometry drift and a relocalisation jump, worker.pipeline.drift). ATE is against
the true poses (Sim(3)-aligned); PSNR over the non-keyframes after the final refinement (`flashmono run` settings,
preset rgbd, but the final refinement unbounded in time so that PSNR does not depend on the machine's load).

`python -m bench device_poses [--modes rgbd_ignore,rgbd_seeded_gt,...] [--frames N] [--size WxH]`
"""

from __future__ import annotations

import argparse
import tempfile
import time

from bench.slam import DRIFT, _source

# A relocalisation jump on top of the drift: 15 cm and 4 degrees at frame 120 (ARKit re-anchoring its map).
JUMP = {"jump_frame": 120, "jump_translation": 0.15, "jump_rotation_deg": 4.0}
MODES = {  # name: (depth, poses given, pose_mode, device poses drifted)
    "rgbd_ignore": (True, False, "prior", False),
    "rgbd_fixed_gt": (True, True, "fixed", False),
    "rgbd_prior_gt": (True, True, "prior", False),
    "rgbd_seeded_gt": (True, True, "seeded", False),
    "rgbd_prior_drift": (True, True, "prior", True),
    "rgbd_seeded_drift": (True, True, "seeded", True),
    "rgb_ignore": (False, False, "prior", False),
    "rgb_prior_gt": (False, True, "prior", False),
    "rgb_seeded_gt": (False, True, "seeded", False),
    "rgb_prior_drift": (False, True, "prior", True),
    "rgb_seeded_drift": (False, True, "seeded", True),
}


def main(argv: list[str]) -> int:
    from worker.config import SlamConfig
    from worker.offline import run_sequence
    from worker.pipeline.drift import PoseDrift

    parser = argparse.ArgumentParser(prog="python -m bench device_poses")
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--drift-seed", type=int, default=0)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    source, stride = _source(1)
    print(f"source {source} at {width}x{height}; drift {DRIFT} + jump {JUMP}, seed {args.drift_seed}")
    print("| mode | keyframes | loops | ATE (cm) | device poses' ATE (cm) | PSNR | depth L1 (cm) | FPS streaming | "
          "wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for mode in args.modes.split(","):
        depth, posed, pose_mode, drifted = MODES[mode]
        # the final refinement runs all its passes whatever the load (its 25 s budget would make PSNR depend on it)
        config = SlamConfig.preset("rgbd", input={"pose_mode": pose_mode}, mapping={"final_refine_budget_s": 0})
        drift = PoseDrift(**DRIFT, **JUMP, seed=args.drift_seed) if drifted else None
        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as out:
            m = run_sequence(source, out, config, use_gt_depth=depth, use_gt_poses=posed, stride=stride,
                             max_frames=args.frames, resize=(width, height), drift=drift)
        wall = time.perf_counter() - start

        def cm(v):
            return "-" if v is None else f"{100 * v:.2f}"

        print(f"| {mode} | {m['num_keyframes']} | {m['loops']} | {cm(m['ate_rmse'])} | "
              f"{cm(m.get('ate_rmse_drift_only'))} | {m['psnr']:.2f} | {cm(m['depth_l1'])} | "
              f"{m['fps_streaming']:.1f} | {wall:.0f} |", flush=True)
    return 0
