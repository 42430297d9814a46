"""Loop detection and relocalization on ICL living room (tests/data/icl_mini, 71 frames at 320x240).

Both descriptors of worker.loop.descriptors are measured on the same keyframes at the tiny model's input size:
describe time, query time against the whole database, and retrieval quality judged by ground truth (the top-1
candidate's true view overlap relative to the best overlap available outside the exclusion window). Also times one
hidden-state relocalization forward pass of the `tiny` model and one PnP relocalization.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import torch

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


def _orb_query_scaling(images, sizes: list[int]) -> None:
    """ORB query time against large databases (copies of the ICL keyframes), vocabulary shortlist vs verify-all."""
    with_vocabulary = OrbDescriptor()
    for label, descriptor in ((f"vocabulary shortlist {with_vocabulary.shortlist} above "
                               f"{with_vocabulary.shortlist_above}", with_vocabulary),
                              ("verify every entry", OrbDescriptor(vocabulary=None))):
        features = [descriptor.describe(image) for image in images]
        for n in sizes:
            database = [features[k % len(features)] for k in range(n)]
            descriptor.similarities(features[-1], database[:2])  # warm-up (bags, ORB objects)
            t0 = time.perf_counter()
            descriptor.similarities(features[-1], database)
            print(f"orb query, database {n:5d}, {label}: {1e3 * (time.perf_counter() - t0):8.1f} ms", flush=True)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench loop_detection")
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--descriptors", default="encoder_gem,orb", help="comma-separated subset to measure")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--scaling", default="100,500,2000", help="database sizes for the ORB query-time scaling")
    args = parser.parse_args(argv)
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
    if "orb" in wanted and args.scaling:
        _orb_query_scaling(images, [int(n) for n in args.scaling.split(",")])
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
