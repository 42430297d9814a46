"""The `flashmono` command line.

Each sub-command lives in its own module under `client/commands/` and exposes
`register(subparsers) -> None`, which adds its parser and sets `func` (called with the parsed namespace and
returning an exit code). Modules are discovered at start-up, so adding a command touches no shared file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import client.commands


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every discovered sub-command."""
    parser = argparse.ArgumentParser(
        prog="flashmono",
        description="Flash-Mono: real-time monocular 2D Gaussian-splatting SLAM, as a library, a CLI and a service.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(client.commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"client.commands.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
