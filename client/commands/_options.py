"""Options and error handling shared by the CLI's client commands (stream, sessions, trajectory, render, export).

Kept free of heavy imports: it is loaded while the parser is built.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
from collections.abc import Callable
from typing import Any

DEFAULT_SERVER = "http://127.0.0.1:8000"


def add_server_options(parser: argparse.ArgumentParser) -> None:
    """--server and --api-key, defaulting to $FLASHMONO_SERVER and $FLASHMONO_API_KEY."""
    parser.add_argument("--server", default=os.environ.get("FLASHMONO_SERVER", DEFAULT_SERVER),
                        help="gateway URL (default: $FLASHMONO_SERVER or %(default)s)")
    parser.add_argument("--api-key", default=os.environ.get("FLASHMONO_API_KEY"),
                        help="API key sent as X-API-Key (default: $FLASHMONO_API_KEY; none when auth is off)")


def make_client(args: argparse.Namespace) -> Any:
    from client.sdk import FlashMonoClient

    return FlashMonoClient(args.server, api_key=args.api_key)


def parse_size(text: str) -> tuple[int, int]:
    """'320x240' -> (320, 240)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 320x240, got {text!r}") from err
    if width <= 0 or height <= 0:
        raise argparse.ArgumentTypeError("width and height must be positive")
    return width, height


def reports_errors(func: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """Turn SDK errors and bad values into a one-line message on stderr and exit code 1."""

    @functools.wraps(func)
    def wrapper(args: argparse.Namespace) -> int:
        from client.errors import FlashMonoError

        try:
            return func(args)
        except FlashMonoError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
        except (ValueError, OSError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 1

    return wrapper


def write_output(data: bytes | str, out: str | None) -> None:
    """Write to the file `out`, or to stdout when `out` is None or '-'."""
    if out in (None, "-"):
        if isinstance(data, bytes):
            sys.stdout.buffer.write(data)
        else:
            sys.stdout.write(data)
        sys.stdout.flush()
        return
    mode = "wb" if isinstance(data, bytes) else "w"
    with open(out, mode) as f:
        f.write(data)
