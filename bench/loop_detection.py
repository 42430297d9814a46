"""Loop detection and relocalization on ICL living room (tests/data/icl_mini, 71 frames at 320x240).

Both descriptors of worker.loop.descriptors are measured on the same keyframes at the tiny model's input size:
describe time, query time against the whole database, and retrieval quality judged by ground truth (the top-1
candidate's true view overlap relative to the best overlap available outside the exclusion window). Also times one
hidden-state relocalization forward pass of the `tiny` model and one PnP relocalization, and the loop closure time
per keyframe (ORB, inverted index, PnP on depth) against the keyframe count up to 1,000 (`--only-long` for just that).
"""

from __future__ import annotations

import argparse
import copy
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import torch

from bench.record import Recorder
from worker.frontend import build_model
from worker.frontend.preprocess import prepare_image
from worker.frontend.tracker import SubmapTracker, TrackerConfig
from worker.loop.descriptors import EncoderGeMDescriptor, OrbDescriptor
from worker.loop.detector import LoopDetector
from worker.loop.oracle import OracleModel, ground_truth_overlap, load_rgbd_folder
from worker.loop.pnp import PnPRelocalizer

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "icl_mini"


def _overlap_table(frames, window: int) -> np.ndarray:
    """Ground-truth view overlap [j, i] for every pair outside the exclusion window."""
    n = len(frames)
    table = np.zeros((n, n))
    for j in range(n):
        for i in range(j - window):
            table[j, i] = ground_truth_overlap(frames, i, j)
    return table


def _retrieval(descriptor, images, overlap: np.ndarray, window: int) -> dict[str, float]:
    detector = LoopDetector(descriptor, exclusion_window=window, top_k=1, min_score=0.0)
    describe_s, query_s, ratios, top1 = [], [], [], []
    for n, image in enumerate(images):
        t0 = time.perf_counter()
        d = descriptor.describe(image)
        t1 = time.perf_counter()
        candidates = detector.query(n, descriptor=d)
        t2 = time.perf_counter()
        detector.add(n, descriptor=d)
        describe_s.append(t1 - t0)
        if candidates:
            query_s.append(t2 - t1)
            best = overlap[n, : n - window].max()
            got = overlap[n, candidates[0].match]
            ratios.append(got / best)
            top1.append(got)
    return {"describe_ms": 1e3 * float(np.median(describe_s)), "query_ms": 1e3 * float(np.median(query_s)),
            "db_size": len(images), "overlap_ratio": float(np.mean(ratios)), "top1_overlap": float(np.mean(top1)),
            "queries": len(ratios)}


def _long_session(sizes: list[int], queries: int, shortlist: int | None,
                  recorder: Recorder | None = None) -> None:
    """Loop closure time per keyframe against the keyframe count, in RGB-D mode (ORB + index + PnP on depth): a
    database of N keyframes re-adds the ICL keyframes under new ids (every pass revisits the room, like a camera
    played forward and back), then `queries` more keyframes go through LoopCloser.process_keyframe."""
    from worker.config import LoopConfig
    from worker.data import open_source
    from worker.pipeline.loop_closer import DepthKeyframePoints, LoopCloser
    from worker.pipeline.stage_times import StageTimes

    class CpuStageTimes(StageTimes):
        """Process CPU time per stage: the machine is shared, and wall time measures the other users too."""

        @contextmanager
        def measure(self, stage: str) -> Iterator[None]:
            start = time.process_time()
            try:
                yield
            finally:
                self.add(stage, time.process_time() - start)

    frames = list(open_source(DATA, use_gt_depth=True))
    images = [torch.from_numpy(f.image).permute(2, 0, 1)[None].float() / 255.0 for f in frames]
    intrinsics = frames[0].intrinsics
    cfg = LoopConfig() if shortlist is None else LoopConfig(shortlist=shortlist)
    for size in sizes:
        depth_points = DepthKeyframePoints()
        closer = LoopCloser(cfg, depth_points=depth_points)
        descriptors = [closer.detector.descriptor.describe(image) for image in images]
        depths = [torch.from_numpy(f.depth) for f in frames]
        for key in range(size):  # key k shows frame k % 71, 3 frames apart: one pass of the room per 71 keys
            source = key % len(frames)
            descriptor = copy.copy(descriptors[source])
            closer.detector.add(3 * key, descriptor=descriptor)
            if closer.pnp is not None:
                closer.pnp.add_keyframe(3 * key, images[source], descriptor)
            depth_points.add(3 * key, depths[source], intrinsics.matrix())
        detection, relocalization, loops = [], [], 0
        for q in range(queries):
            key = size + q
            source = key % len(frames)
            depth_points.add(3 * key, depths[source], intrinsics.matrix())
            closer.timings = CpuStageTimes()
            closer.last_loop_keyframe_count = -10**9  # every query may close a loop (no cooldown)
            loops += bool(closer.process_keyframe(3 * key, images[source], intrinsics))
            detection.append(closer.timings.seconds["loop_detection"])
            relocalization.append(closer.timings.seconds.get("loop_relocalization", 0.0))
        total = np.add(detection, relocalization)
        print(f"keyframes {size:5d}: CPU per keyframe: loop detection median {1e3 * np.median(detection):7.1f} ms, "
              f"relocalization {1e3 * np.median(relocalization):6.1f} ms, together {1e3 * np.median(total):7.1f} ms "
              f"({loops}/{queries} closed a loop)", flush=True)
        if recorder is not None:
            mode = "loop detection per keyframe" + ("" if shortlist is None else f" (shortlist {shortlist})")
            recorder.write({"area": "loop", "sequence": f"{size:,} keyframes", "mode": mode},
                           {"latency_ms": round(1e3 * float(np.median(detection)), 1),
                            "relocalization_ms": round(1e3 * float(np.median(relocalization)), 1),
                            "loops_closed": loops, "queries": queries})


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench loop_detection")
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--descriptors", default="encoder_gem,orb", help="comma-separated subset to measure")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--long", default="50,100,200,500,1000",
                        help="keyframe counts for the loop-closure time per keyframe (empty: skip)")
    parser.add_argument("--queries", type=int, default=5, help="keyframes timed at each count")
    parser.add_argument("--shortlist", type=int, default=None, help="LoopConfig.shortlist (default: the config's)")
    parser.add_argument("--only-long", action="store_true", help="only the time per keyframe against the count")
    args = parser.parse_args(argv)
    recorder = Recorder("loop_detection", argv)
    if args.only_long:
        torch.set_num_threads(args.threads)
        _long_session([int(n) for n in args.long.split(",")], args.queries, args.shortlist, recorder)
        return 0
    torch.set_num_threads(args.threads)
    frames = load_rgbd_folder(DATA)
    overlap = _overlap_table(load_rgbd_folder(DATA, downscale=4), args.window)
    rgb = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in sorted((DATA / "rgb").glob("*.jpg"))]
    torch.manual_seed(0)
    model = build_model("tiny").eval()
    images = [prepare_image(im, long_side=model.config.image_long_side).tensor for im in rgb]
    print(f"{len(images)} keyframes at {tuple(images[0].shape[2:])}, exclusion window {args.window} frames")
    wanted = set(args.descriptors.split(","))
    for descriptor in (EncoderGeMDescriptor(model), OrbDescriptor()):
        if descriptor.name not in wanted:
            continue
        r = _retrieval(descriptor, images, overlap, args.window)
        print(f"{descriptor.name:12s} describe {r['describe_ms']:6.1f} ms  query {r['query_ms']:6.1f} ms "
              f"(database up to {r['db_size']})  top-1 true overlap {r['top1_overlap']:.3f} = "
              f"{100 * r['overlap_ratio']:.1f}% of the best available ({r['queries']} queries)")
        recorder.write({"sequence": "icl_mini", "mode": f"retrieval, {descriptor.name}",
                        "variant": f"window {args.window}"},
                       {k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()})
    if "orb" in wanted and args.long:
        _long_session([int(n) for n in args.long.split(",")], args.queries, args.shortlist, recorder)
    with torch.no_grad():
        state = model.init_state(1)
        for image in images[:8]:
            state = model.step(image, state).state
        times = []
        for image in images[60:65]:
            t0 = time.perf_counter()
            model.step(image, state, update=False)
            times.append(time.perf_counter() - t0)
    print(f"hidden-state relocalization forward pass (tiny, untrained): median {1e3 * np.median(times):.0f} ms")
    tracker = SubmapTracker(OracleModel(frames), TrackerConfig(submap_length=2))
    tracker.track(12, frames[12].image, frames[12].intrinsics)
    tracker.track(35, frames[35].image, frames[35].intrinsics)
    pnp = PnPRelocalizer(tracker)
    pnp.add_keyframe(12, frames[12].image)
    t0 = time.perf_counter()
    c = pnp.relocalize(12, 35, frames[35].image, frames[35].intrinsics)
    print(f"PnP relocalization (320x240, ORB 1000): {1e3 * (time.perf_counter() - t0):.0f} ms, "
          f"{c.extra.get('inliers', 0)} inliers, accepted={c.accepted}")
    return 0
