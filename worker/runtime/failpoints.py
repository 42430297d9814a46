"""Crash injection for tests: `failpoint(name)` ends the process on the spot (like a kill -9, without cleanup)
when `name` is listed in FLASHMONO_FAILPOINTS (comma-separated). Unset in production: a set lookup, nothing else.

The tests use it to crash a worker or the gateway between the steps of finishing and deleting a session, and
check that no such crash leaves a session stuck or a half-deleted record behind.
"""

from __future__ import annotations

import os

_ACTIVE = frozenset(filter(None, (p.strip() for p in os.environ.get("FLASHMONO_FAILPOINTS", "").split(","))))
CRASH_EXIT_CODE = 86


def failpoint(name: str) -> None:
    """Exit the process at once (exit code 86) when `name` is an active failpoint."""
    if name in _ACTIVE:
        os._exit(CRASH_EXIT_CODE)
