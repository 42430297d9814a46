"""Run benchmarks: `python -m bench [NAME ...] [-- OPTIONS]` (all modules when no name is given).

Leading arguments without a dash name modules `bench/<name>.py`; the remaining arguments are passed to each
module's `main(argv)`.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

ALIASES = {"long": "long_session"}  # `python -m bench long` runs bench/long_session.py


def main(argv: list[str]) -> int:
    split = next((i for i, a in enumerate(argv) if a.startswith("-")), len(argv))
    names, options = argv[:split], [a for a in argv[split:] if a != "--"]
    if not names:
        names = sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if m.name != "__main__")
    status = 0
    for name in names:
        module = importlib.import_module(f"bench.{ALIASES.get(name, name)}")
        if hasattr(module, "main"):
            print(f"== bench.{name}", flush=True)
            status |= int(module.main(options) or 0)
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
