"""Pipelined streaming into a server that cannot keep up (issue 17): 211 ICL frames at 30 FPS, sent without waiting
for acks, by the SDK and by an independent client written from the protocol text, into a real stack with a queue
of 4 frames and a passthrough worker taking 40 ms a frame. Reports frames lost (target 0), order, re-sends and
time; and the map PLY's bytes per surfel with and without the 45 zero SH coefficients. `python -m bench pipelined`."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
FRAMES, FPS = 211, 30.0


def _frames():
    import cv2

    from worker.data.frame import Frame

    paths = sorted((REPO_ROOT / "tests" / "data" / "icl_mini" / "rgb").glob("*.jpg"))[:12]
    images = [cv2.resize(cv2.imread(str(p))[..., ::-1], (160, 120), interpolation=cv2.INTER_AREA) for p in paths]
    poses = []
    for i in range(FRAMES):
        pose = np.eye(4)
        pose[0, 3] = float(i)  # the passthrough engine echoes it: which frame a pose belongs to
        poses.append(pose)
    return [Frame(index=i, timestamp=i / FPS, image=np.ascontiguousarray(images[i % 12]), pose=poses[i])
            for i in range(FRAMES)]


def _lost_and_order(seqs: list[int], xs: list[float]) -> tuple[int, bool]:
    lost = FRAMES - len(set(seqs))
    return lost, seqs == sorted(seqs) and xs == [float(s) for s in seqs]


def bench_streams() -> list[tuple[str, dict]]:
    sys.path.insert(0, str(REPO_ROOT / "tests"))
    import httpx
    import msgpack
    from live_stack import LiveStack
    from raw_stream_client import RawPipelinedClient

    from client.sdk import FlashMonoClient
    from client.streaming import WireOptions, encode_frame_message

    frames = _frames()
    env = {"FLASHMONO_MAX_QUEUE": "4", "FLASHMONO_PASSTHROUGH_DELAY_MS": "40"}
    rows = []
    with LiveStack(workers=1, engine="passthrough", extra_env=env) as stack:
        with FlashMonoClient(stack.url) as client:
            session = client.create_session(name="bench-sdk")
            start = time.monotonic()
            summary = client.stream(session.id, frames, fps=FPS, window=8, max_pending=16,
                                    wire=WireOptions(send_intrinsics=False, send_pose=True))
            lost, ordered = _lost_and_order([p.seq for p in summary.poses], [p.pose[0, 3] for p in summary.poses])
            rows.append(("SDK", {"lost": lost, "ordered": ordered, "resent": summary.backpressure_retries,
                                 "seconds": time.monotonic() - start}))
        wire = WireOptions(send_intrinsics=False, send_pose=True)
        messages = [encode_frame_message(f, i, wire) for i, f in enumerate(frames)]
        assert all(msgpack.unpackb(m)["seq"] == i for i, m in enumerate(messages[:3]))
        session_id = httpx.post(f"{stack.url}/v1/sessions", json={"name": "bench-raw"}).json()["id"]
        raw = RawPipelinedClient(f"ws://127.0.0.1:{stack.port}/v1/sessions/{session_id}/stream", messages, FPS)
        start = time.monotonic()
        raw.run()
        lost, ordered = _lost_and_order([p["seq"] for p in raw.poses], [p["pose"][3] for p in raw.poses])
        rows.append(("independent client", {"lost": lost, "ordered": ordered, "resent": raw.rewinds,
                                            "seconds": time.monotonic() - start}))
    return rows


def bench_ply_bytes() -> dict[str, float]:
    import torch

    from worker.mapping import Surfels
    from worker.mapping.ply import ply_with_sh_degree, surfels_to_ply_bytes

    n = 50_000
    gen = torch.Generator().manual_seed(0)
    surfels = Surfels(means=torch.randn(n, 3, generator=gen),
                      quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
                      scales=torch.rand(n, 2, generator=gen) * 0.01, opacities=torch.rand(n, generator=gen),
                      colors=torch.rand(n, 3, generator=gen), keyframe_ids=torch.zeros(n, dtype=torch.int64))
    full = surfels_to_ply_bytes(surfels)
    start = time.perf_counter()
    compact = ply_with_sh_degree(full, 0)
    strip_ms = (time.perf_counter() - start) * 1000
    return {"sh3": len(full) / n, "sh0": len(compact) / n, "strip_ms": strip_ms}


def main(argv: list[str]) -> int:
    failed = 0
    for name, row in bench_streams():
        print(f"{name:20s} {FRAMES} frames at {FPS:.0f} FPS: lost {row['lost']}, order kept {row['ordered']}, "
              f"{row['resent']} re-sends/rewinds, {row['seconds']:.1f} s")
        failed |= row["lost"] != 0 or not row["ordered"]
    ply = bench_ply_bytes()
    print(f"map PLY: {ply['sh0']:.1f} bytes/surfel (sh_degree 0, default) vs {ply['sh3']:.1f} (sh_degree 3); "
          f"stripping 50k surfels takes {ply['strip_ms']:.0f} ms")
    return int(failed)
