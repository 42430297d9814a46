"""`flashmono export ID`: download a session's 2D Gaussian surfel map as PLY, SPZ or .splat."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from client.commands._options import add_server_options, make_client, reports_errors, write_output
from client.rest import MAP_FORMATS


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export", help="download a session's map (PLY, SPZ or .splat)",
        description="Download the session's 2D Gaussian surfel map (positions, orientations, scales, opacities, "
                    "colours) for a Gaussian-splatting viewer: binary PLY (68 bytes a surfel), Niantic SPZ v3 "
                    "(about 10) or antimatter15 .splat (32). The format follows --format, else the --out suffix.")
    parser.add_argument("session_id", metavar="ID", help="session id")
    add_server_options(parser)
    parser.add_argument("--out", default=None, help="output file, '-' for stdout (default map.FORMAT)")
    parser.add_argument("--format", choices=MAP_FORMATS, default=None,
                        help="ply, spz or splat (default: the --out suffix, else ply)")
    parser.add_argument("--sh-degree", type=int, choices=(0, 3), default=0,
                        help="0: colour as f_dc only, 68 bytes a surfel; 3: with the 45 zero f_rest coefficients "
                             "fixed-record 3DGS readers (SIBR) expect, 248 bytes (default %(default)s)")
    parser.set_defaults(func=run)


def chosen_format(out: str | None, fmt: str | None) -> tuple[str, str]:
    """(format, output path): --format wins, else the suffix of --out, else PLY."""
    suffix = Path(out).suffix.lstrip(".").lower() if out and out != "-" else ""
    fmt = fmt or (suffix if suffix in MAP_FORMATS else "ply")
    return fmt, out or f"map.{fmt}"


@reports_errors
def run(args: argparse.Namespace) -> int:
    fmt, out = chosen_format(args.out, args.format)
    with make_client(args) as client:
        data = client.download_map(args.session_id, sh_degree=args.sh_degree, format=fmt)
    write_output(data, out)
    if out != "-":
        print(f"wrote {len(data)} bytes ({fmt}) to {out}", file=sys.stderr)
    return 0
