"""Starting mapping processes: forked from a server process that has imported the engine once (multiprocessing's
forkserver with the mapping side preloaded), so a session's mapping process is ready in tens of milliseconds rather
than the seconds a fresh interpreter takes to import torch, and shares those pages with its siblings."""

from __future__ import annotations

import multiprocessing
import sys
import threading
from multiprocessing.context import BaseContext
from multiprocessing.process import BaseProcess

from worker.config import SlamConfig
from worker.pipeline.mapping_process import child
from worker.pipeline.mapping_process.channel import Channel

_context: BaseContext | None = None
_context_lock = threading.Lock()


def _mapping_context() -> BaseContext:
    global _context
    with _context_lock:
        if _context is None:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(["worker.pipeline.mapping_process.preload"])
            _context = context
        return _context


def _ready() -> None:
    """The probe forked once at start-up: its fork returns only after the server's imports, which it checks."""
    loaded = all(name in sys.modules for name in ("worker.pipeline.mapping_process.preload", "torch._dynamo"))
    sys.exit(0 if loaded else 1)


def prestart(timeout_s: float = 120.0) -> bool:
    """Start the fork server now and wait for its imports (the engine, ~3 s of a core), so that neither the first
    session's first frames nor the worker's readiness come before them. True once a probe process has forked and
    exited cleanly."""
    probe = _mapping_context().Process(target=_ready, name="flashmono-mapping-probe", daemon=True)
    probe.start()  # starts the server (ensure_running) and blocks until it has preloaded and forked
    probe.join(timeout_s)
    return probe.exitcode == 0


def start_mapping_process(config: SlamConfig) -> tuple[BaseProcess, Channel]:
    """A new mapping process for a session with `config`, initialised: (the process, the session's channel)."""
    context = _mapping_context()
    ours, theirs = context.Pipe(duplex=True)
    process = context.Process(target=child.serve, args=(theirs,), name="flashmono-mapping", daemon=True)
    process.start()
    theirs.close()  # the process holds its end: when it dies, our end reads EOF
    channel = Channel(ours, outbox=True)
    channel.send({"op": "init", "config": config.model_dump(mode="json")})
    return process, channel
