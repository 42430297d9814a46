"""The worker's memory budget: its resident size and its mapping processes', read cheaply enough to check before
taking each session."""

from __future__ import annotations

import os
import resource


def resident_mb() -> float:
    """This process's resident set size plus the proportional set size of every process it started, directly or
    through a fork server (sessions' mapping processes, worker.pipeline.mapping_process), in MiB. Pages those
    processes share are counted once between them (proportional set size). /proc on Linux; elsewhere this process's
    peak from getrusage."""
    try:
        with open("/proc/self/statm", "rb") as statm:
            pages = int(statm.read().split()[1])
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20 + sum(proportional_mb(pid)
                                                            for pid in descendants(os.getpid()))


def over_budget(budget_mb: int) -> bool:
    """True when a budget is set (> 0) and the process with its descendants is above it."""
    return budget_mb > 0 and resident_mb() > budget_mb


def descendants(root: int) -> list[int]:
    """The ids of `root`'s children, their children and so on (from /proc; empty where there is none)."""
    children: dict[int, list[int]] = {}
    try:
        entries = [entry for entry in os.listdir("/proc") if entry.isdigit()]
    except OSError:
        return []
    for entry in entries:
        try:
            with open(f"/proc/{entry}/stat", "rb") as stat:
                fields = stat.read().rsplit(b")", 1)[1].split()
        except (OSError, IndexError):
            continue  # gone meanwhile
        children.setdefault(int(fields[1]), []).append(int(entry))
    found, stack = [], [root]
    while stack:
        kids = children.get(stack.pop(), [])
        found += kids
        stack += kids
    return found


def proportional_mb(pid: int) -> float:
    """A process's proportional set size in MiB (0 when it is gone or the kernel does not say)."""
    try:
        with open(f"/proc/{pid}/smaps_rollup", "rb") as rollup:
            for line in rollup:
                if line.startswith(b"Pss:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0.0
