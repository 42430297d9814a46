"""Worker process entry point: `python -m worker.runtime.main` (or via `flashmono serve`).

Configured by the environment and flags (a flag overrides its variable): every option, its variable, default and
bounds are in `python -m worker.runtime.main --help`, generated from `worker.runtime.settings.WorkerSettings`, where
each is defined once. REDIS_URL (`redis+cluster://host:port,...` for a Redis Cluster) is required here.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import sys
import uuid

from protocol.settings_model import option_parser, parse_settings
from worker.runtime.settings import WorkerSettings


def build_parser() -> argparse.ArgumentParser:
    return option_parser(WorkerSettings, prog="flashmono-worker",
                           description="Flash-Mono worker (Redis streams). Each option also reads the environment "
                                       "variable named in brackets; a flag given overrides it.")


def main(argv: list[str] | None = None) -> int:
    settings: WorkerSettings = parse_settings(WorkerSettings, argv, build_parser())
    logging.basicConfig(level=settings.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not settings.redis_url:
        print("error: REDIS_URL (or --redis-url) is required for a worker", file=sys.stderr)
        return 2
    sys.setswitchinterval(settings.switch_interval_ms / 1000.0)
    if settings.torch_threads > 0:
        import torch

        torch.set_num_threads(settings.torch_threads)
    from redis.backoff import NoBackoff
    from redis.retry import Retry

    from worker.runtime.connection import connect
    from worker.runtime.consumer import Worker

    worker_id = settings.worker_id or f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    # No silent retries inside redis-py: a lost connection surfaces to the worker's loops, which wait the outage
    # out and resume each session from its snapshot (a retried XREADGROUP could lose the entries of its reply).
    # REDIS_URL may name a Redis Cluster (redis+cluster://host:port,...): see worker.runtime.connection
    client = connect(settings.redis_url, health_check_interval=30, retry=Retry(NoBackoff(), 0))
    worker = Worker(client, worker_id, settings.runtime)
    signal.signal(signal.SIGTERM, lambda *_: worker.shutdown())
    signal.signal(signal.SIGINT, lambda *_: worker.shutdown())
    worker.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
