"""Client SDK figures: frame encoding cost (JPEG + depth PNG + msgpack) and end-to-end streaming throughput of
the SDK against a real stack whose worker runs the passthrough engine (so the figure is the client + service path,
not the SLAM compute). `python -m bench client`."""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def bench_encoding(frames, options, repeats: int = 3) -> float:
    from client.streaming import encode_frame_message

    timings = []
    for _ in range(repeats):
        start = time.perf_counter()
        for i, frame in enumerate(frames):
            encode_frame_message(frame, i, options)
        timings.append((time.perf_counter() - start) / len(frames))
    return statistics.median(timings) * 1000


def bench_streaming(frames, options) -> dict:
    sys.path.insert(0, str(REPO_ROOT / "tests"))
    from live_stack import LiveStack

    from client.sdk import FlashMonoClient

    with LiveStack(workers=1, engine="passthrough") as stack, FlashMonoClient(stack.url) as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, name="bench")
        summary = client.stream(session.id, frames, wire=options, window=8, max_pending=32)
        return {"frames": summary.frames_sent, "fps": summary.fps, "retries": summary.backpressure_retries,
                "max_queue": summary.max_queue_depth}


def main(argv: list[str]) -> int:
    from client.streaming import WireOptions, open_frames

    frames = list(open_frames(REPO_ROOT / "tests" / "data" / "icl_mini", use_gt_poses=True))
    rgb = WireOptions()
    rgbd = WireOptions(send_depth=True, send_pose=True)
    print(f"encode 320x240 JPEG q90:              {bench_encoding(frames, rgb):6.2f} ms/frame")
    print(f"encode 320x240 JPEG + depth + pose:   {bench_encoding(frames, rgbd):6.2f} ms/frame")
    result = bench_streaming(frames, rgb)
    print(f"stream {result['frames']} frames (passthrough worker): {result['fps']:6.1f} frames/s end to end, "
          f"{result['retries']} backpressure re-sends, max queue depth {result['max_queue']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
