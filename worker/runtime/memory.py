"""The worker's memory budget: its resident size, read cheaply enough to check before taking each session."""

from __future__ import annotations

import os
import resource


def resident_mb() -> float:
    """This process's resident set size in MiB (/proc on Linux; the peak from getrusage elsewhere)."""
    try:
        with open("/proc/self/statm", "rb") as statm:
            pages = int(statm.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def over_budget(budget_mb: int) -> bool:
    """True when a budget is set (> 0) and the process is above it."""
    return budget_mb > 0 and resident_mb() > budget_mb
