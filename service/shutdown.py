"""SIGTERM (what `kill`, systemd and `docker stop` send) as a clean exit, like Ctrl-C.

Python's default SIGTERM action ends the process at once: `finally` blocks do not run, so a server's child
processes and temp dirs would outlive it. uvicorn handles SIGTERM while it serves, then restores the previous
handler and raises the signal again; with `exit_on_sigterm()` installed, that re-raised signal unwinds the stack.
"""

from __future__ import annotations

import logging
import signal
from types import FrameType

log = logging.getLogger(__name__)


class Terminated(SystemExit):
    """Raised in the main thread on the first SIGTERM; exits with status 0 once cleanup has run."""


def exit_on_sigterm() -> None:
    """Make the first SIGTERM raise `Terminated` in the main thread; later ones are logged and ignored while the
    cleanup runs. Call from the main thread."""
    received = False

    def handler(signum: int, frame: FrameType | None) -> None:
        nonlocal received
        if received:
            log.warning("SIGTERM again: still shutting down")
            return
        received = True
        log.info("SIGTERM: shutting down")
        raise Terminated(0)

    signal.signal(signal.SIGTERM, handler)
