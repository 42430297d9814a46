"""Starting mapping processes: forked from a server process that has imported the engine once (multiprocessing's
forkserver with the mapping side preloaded), so a session's mapping process is ready in tens of milliseconds rather
than the seconds a fresh interpreter takes to import torch, and shares those pages with its siblings."""

from __future__ import annotations

import multiprocessing
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


def prestart() -> None:
    """Start the fork server now (it imports the engine, ~3 s of a core), not under a session's first frames."""
    from multiprocessing import forkserver

    _mapping_context()
    forkserver.ensure_running()


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
