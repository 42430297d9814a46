"""Worker process entry point: `python -m worker.runtime.main` (or via `flashmono serve`).

Environment (flags override): REDIS_URL (required here; `redis+cluster://host:port,...` for a Redis Cluster),
FLASHMONO_WORKER_ID, FLASHMONO_ENGINE (slam|passthrough),
FLASHMONO_LEASE_TTL_MS (2500: a dead worker's sessions resume elsewhere within seconds),
FLASHMONO_SNAPSHOT_EVERY (keyframes between snapshots, 5), FLASHMONO_SNAPSHOT_EVERY_S (or seconds, 1; 0: off),
FLASHMONO_MAX_SESSIONS (sessions per worker, 16), FLASHMONO_TORCH_THREADS (torch intra-op threads),
FLASHMONO_MAX_FRAME_SIDE (640), FLASHMONO_MAX_FRAME_ATTEMPTS (2), FLASHMONO_MEMORY_BUDGET_MB (0: none),
FLASHMONO_IDLE_TIMEOUT_S (600; 0: never), FLASHMONO_TRANSIENT_TTL_S (3600), FLASHMONO_RETENTION_S (0: kept),
FLASHMONO_BLOB_DIR (none), FLASHMONO_ARCHIVE_AFTER_S (3600), FLASHMONO_SKIP_AFTER_MS (100: a frame that waited
longer while a newer one is waiting is skipped, newest first wins; 0: never), FLASHMONO_MAX_CONSECUTIVE_SKIPS (5),
FLASHMONO_MAX_SKIPPED_SPAN_MS (170: after the first, no frame in a row is skipped that arrived longer after the last
tracked one),
FLASHMONO_TRACKING_SIDE (0: sessions that name no tracking resolution track as their settings choose),
FLASHMONO_CHECKPOINT (trained frontend weights; with a CUDA GPU, sessions that name no preset get the paper's settings),
FLASHMONO_SWITCH_INTERVAL_MS (1).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import sys
import uuid

from redis.backoff import NoBackoff
from redis.retry import Retry

from worker.runtime.connection import connect
from worker.runtime.consumer import Worker
from worker.runtime.engine import ENGINE_KINDS
from worker.runtime.sessions import RuntimeConfig


def build_parser() -> argparse.ArgumentParser:
    env = os.environ.get
    parser = argparse.ArgumentParser(prog="flashmono-worker", description="Flash-Mono worker (Redis streams).")
    parser.add_argument("--redis-url", default=env("REDIS_URL"))
    parser.add_argument("--worker-id", default=env("FLASHMONO_WORKER_ID"))
    parser.add_argument("--engine", choices=ENGINE_KINDS, default=env("FLASHMONO_ENGINE", "slam"))
    parser.add_argument("--lease-ttl-ms", type=int, default=int(env("FLASHMONO_LEASE_TTL_MS", "2500")))
    parser.add_argument("--snapshot-every", type=int, default=int(env("FLASHMONO_SNAPSHOT_EVERY", "5")))
    parser.add_argument("--snapshot-every-s", type=float, default=float(env("FLASHMONO_SNAPSHOT_EVERY_S", "1")),
                        help="also snapshot this often (seconds; 0: by keyframes only): bounds a takeover's replay")
    parser.add_argument("--max-sessions", type=int, default=int(env("FLASHMONO_MAX_SESSIONS", "16")))
    parser.add_argument("--max-frame-side", type=int, default=int(env("FLASHMONO_MAX_FRAME_SIDE", "640")),
                        help="frames are downscaled to this longest side (and to the session's resolution) on decode")
    parser.add_argument("--max-frame-attempts", type=int, default=int(env("FLASHMONO_MAX_FRAME_ATTEMPTS", "2")),
                        help="workers that may die processing one frame before it is quarantined (session failed)")
    parser.add_argument("--memory-budget-mb", type=int, default=int(env("FLASHMONO_MEMORY_BUDGET_MB", "0")),
                        help="take no new session while this process's resident memory is above it (0: no limit)")
    parser.add_argument("--idle-timeout-s", type=float, default=float(env("FLASHMONO_IDLE_TIMEOUT_S", "600")),
                        help="a session without frames this long is abandoned and its slot freed (0: never)")
    parser.add_argument("--transient-ttl-s", type=float, default=float(env("FLASHMONO_TRANSIENT_TTL_S", "3600")),
                        help="an ended session's frames, messages and requests expire after this")
    parser.add_argument("--retention-s", type=float, default=float(env("FLASHMONO_RETENTION_S", "0")),
                        help="an ended session's record, trajectory and map expire after this (0: kept)")
    parser.add_argument("--blob-dir", default=env("FLASHMONO_BLOB_DIR", ""),
                        help="blob store (a directory) finished sessions move to, map and trajectory included")
    parser.add_argument("--archive-after-s", type=float, default=float(env("FLASHMONO_ARCHIVE_AFTER_S", "3600")),
                        help="finished sessions move to --blob-dir this long after finishing (0: never)")
    parser.add_argument("--skip-after-ms", type=float, default=float(env("FLASHMONO_SKIP_AFTER_MS", "100")),
                        help="live tracking: a frame that waited longer than this while a newer frame is waiting is "
                             "skipped with a `skipped` message (newest first wins; 0: never skip)")
    parser.add_argument("--max-consecutive-skips", type=int,
                        default=int(env("FLASHMONO_MAX_CONSECUTIVE_SKIPS", "5")),
                        help="frames skipped in a row at most (tracking keeps its continuity)")
    parser.add_argument("--max-skipped-span-ms", type=float,
                        default=float(env("FLASHMONO_MAX_SKIPPED_SPAN_MS", "170")),
                        help="after the first, no frame in a row is skipped that arrived more than this after the "
                             "last tracked frame (the motion across a gap grows with its time: at 10 frames/s, one in "
                             "a row)")
    parser.add_argument("--tracking-side", type=int, default=int(env("FLASHMONO_TRACKING_SIDE", "0")),
                        help="sessions that name no tracking resolution track frames at most this long a side "
                             "(0: as their settings choose: live streams over 320 px at 320, others as they come)")
    parser.add_argument("--checkpoint", default=env("FLASHMONO_CHECKPOINT", ""),
                        help="trained frontend weights (safetensors, e.g. from `flashmono convert-cut3r`); with a "
                             "CUDA GPU, sessions that name no preset get the paper's settings")
    parser.add_argument("--switch-interval-ms", type=float,
                        default=float(env("FLASHMONO_SWITCH_INTERVAL_MS", "1")),
                        help="the interpreter's thread switch interval: how long the tracking thread may wait for the "
                             "GIL while a mapping or loop thread runs Python (the interpreter's default is 5)")
    parser.add_argument("--torch-threads", type=int, default=int(env("FLASHMONO_TORCH_THREADS", "0")))
    parser.add_argument("--log-level", default=env("FLASHMONO_LOG_LEVEL", "INFO"))
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args.redis_url:
        print("error: REDIS_URL (or --redis-url) is required for a worker", file=sys.stderr)
        return 2
    if min(args.snapshot_every, args.max_sessions, args.max_frame_attempts) < 1 or args.max_frame_side < 32 \
            or args.memory_budget_mb < 0 or args.tracking_side < 0:
        print("error: --snapshot-every, --max-sessions and --max-frame-attempts must be >= 1, --max-frame-side "
              ">= 32, --memory-budget-mb and --tracking-side >= 0", file=sys.stderr)
        return 2
    if args.snapshot_every_s < 0:
        print("error: --snapshot-every-s must be >= 0", file=sys.stderr)
        return 2
    if args.transient_ttl_s < 1 or args.retention_s < 0 or args.idle_timeout_s < 0:
        print("error: --transient-ttl-s must be >= 1 (clients still read the last messages), --retention-s and "
              "--idle-timeout-s >= 0", file=sys.stderr)
        return 2
    if args.switch_interval_ms <= 0:
        print("error: --switch-interval-ms must be > 0", file=sys.stderr)
        return 2
    sys.setswitchinterval(args.switch_interval_ms / 1000.0)
    if args.torch_threads > 0:
        import torch

        torch.set_num_threads(args.torch_threads)
    worker_id = args.worker_id or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    config = RuntimeConfig(engine_kind=args.engine, lease_ttl_ms=args.lease_ttl_ms,
                           snapshot_every_keyframes=args.snapshot_every, snapshot_every_s=args.snapshot_every_s,
                           max_sessions=args.max_sessions,
                           max_frame_side=args.max_frame_side, max_frame_attempts=args.max_frame_attempts,
                           memory_budget_mb=args.memory_budget_mb, idle_timeout_s=args.idle_timeout_s,
                           transient_ttl_s=args.transient_ttl_s, retention_s=args.retention_s,
                           blob_dir=args.blob_dir, archive_after_s=args.archive_after_s,
                           skip_after_ms=args.skip_after_ms, max_consecutive_skips=args.max_consecutive_skips,
                           max_skipped_span_ms=args.max_skipped_span_ms,
                           tracking_side=args.tracking_side, checkpoint=args.checkpoint)
    # No silent retries inside redis-py: a lost connection surfaces to the worker's loops, which wait the outage
    # out and resume each session from its snapshot (a retried XREADGROUP could lose the entries of its reply).
    # REDIS_URL may name a Redis Cluster (redis+cluster://host:port,...): see worker.runtime.connection
    client = connect(args.redis_url, health_check_interval=30, retry=Retry(NoBackoff(), 0))
    worker = Worker(client, worker_id, config)
    signal.signal(signal.SIGTERM, lambda *_: worker.shutdown())
    signal.signal(signal.SIGINT, lambda *_: worker.shutdown())
    worker.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
