"""Result records: one JSON file per benchmark case under `bench/results/`, the data bench/RESULTS.md is made from.

A record is `{"benchmark", "case", "values", "commit", "machine", "load", "command", "date", "source"}`: `case` names
what was measured (`area`, then `sequence`, `mode`, `size`, ... as the area needs), `values` the figures (SI-ish
units in the key's name: `_ms`, `_s`, `_m`, `_db`, `_mib`, `_share`), `load` the 1-minute load average at the start
and at the end, `source` "measured" or where a transcribed figure was read. A benchmark writes them with
`Recorder(benchmark, argv).write(case, values)`.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "bench" / "results"
JOURNAL_DIR = ROOT / "bench" / "journal"
JOURNAL_INBOX = JOURNAL_DIR / "inbox.md"  # where `--write-results` narrative goes now that RESULTS.md is generated
CASE_ORDER = ("area", "sequence", "mode", "size", "variant")
RESULTS_ENV = "FLASHMONO_BENCH_RESULTS"  # another results folder (tests, trial runs): records go to $it/<benchmark>/


def results_dir() -> Path:
    """Where records are written: `$FLASHMONO_BENCH_RESULTS` when set, else bench/results/."""
    return Path(os.environ[RESULTS_ENV]) if os.environ.get(RESULTS_ENV) else RESULTS_DIR


def commit() -> str:
    """The short hash of the checkout's HEAD ("unknown" outside git)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _gpu() -> str | None:
    # nvidia-smi rather than torch: a record must not pay for (or depend on) importing torch
    if shutil.which("nvidia-smi") is None:
        return None
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return out.splitlines()[0].strip() if out else None


def machine() -> dict[str, Any]:
    """Cores this process may use, the CPU model, the GPU (None without one) and Python's version."""
    return {"cores": len(os.sched_getaffinity(0)), "cpu": _cpu_model(), "gpu": _gpu(),
            "python": platform.python_version()}


def loadavg() -> float:
    return round(os.getloadavg()[0], 2)


def case_slug(case: dict[str, Any]) -> str:
    """A file name for a case: its values in CASE_ORDER, then any others, joined by `_`."""
    keys = [k for k in CASE_ORDER if k in case] + sorted(k for k in case if k not in CASE_ORDER)
    return re.sub(r"[^A-Za-z0-9._+-]+", "-", "_".join(str(case[k]) for k in keys)).strip("-")


def make_record(benchmark: str, case: dict[str, Any], values: dict[str, Any], *, load: list[float],
                command: str, **extra: Any) -> dict[str, Any]:
    """A measured record of this machine and checkout now; `extra` (e.g. `note`, `settings`) is kept beside."""
    return {"benchmark": benchmark, "case": dict(case), "values": dict(values), "commit": commit(),
            "machine": machine(), "load": list(load), "command": command, "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "source": "measured", **extra}


class Recorder:
    """Writes a benchmark's records; the load average is taken when it is made (the run's start)."""

    def __init__(self, benchmark: str, argv: list[str] | None = None, folder: Path | None = None) -> None:
        self.benchmark = benchmark
        self.command = " ".join(["python -m bench", benchmark, *(sys.argv[1:] if argv is None else argv)])
        self.folder = folder or results_dir() / benchmark
        self.load_start = loadavg()

    def write(self, case: dict[str, Any], values: dict[str, Any], **extra: Any) -> Path:
        """Write (replace) the case's record: git keeps the earlier ones."""
        record = make_record(self.benchmark, case, values, load=[self.load_start, loadavg()], command=self.command,
                             **extra)
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / f"{case_slug(case)}.json"
        path.write_text(json.dumps(record, indent=1, default=str) + "\n")
        return path


def journal_append(text: str) -> Path:
    """Append narrative (a benchmark's `--write-results` row or section) to the journal's inbox."""
    JOURNAL_INBOX.parent.mkdir(parents=True, exist_ok=True)
    old = JOURNAL_INBOX.read_text() if JOURNAL_INBOX.exists() else "# Inbox: rows benchmarks appended\n"
    JOURNAL_INBOX.write_text(old.rstrip("\n") + "\n" + text.rstrip("\n") + "\n")
    return JOURNAL_INBOX
