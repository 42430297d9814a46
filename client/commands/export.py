"""`flashmono export ID`: download a session's 2D Gaussian surfel map as PLY."""

from __future__ import annotations

import argparse
import sys

from client.commands._options import add_server_options, make_client, reports_errors, write_output


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export", help="download a session's map (PLY)",
        description="Download the session's 2D Gaussian surfel map as a binary PLY (positions, orientations, "
                    "scales, opacities, colours), e.g. for a Gaussian-splatting viewer.")
    parser.add_argument("session_id", metavar="ID", help="session id")
    add_server_options(parser)
    parser.add_argument("--out", default="map.ply", help="output file, '-' for stdout (default %(default)s)")
    parser.add_argument("--sh-degree", type=int, choices=(0, 3), default=0,
                        help="0: colour as f_dc only, 68 bytes a surfel; 3: with the 45 zero f_rest coefficients "
                             "fixed-record 3DGS readers (SIBR) expect, 248 bytes (default %(default)s)")
    parser.set_defaults(func=run)


@reports_errors
def run(args: argparse.Namespace) -> int:
    with make_client(args) as client:
        data = client.download_map(args.session_id, sh_degree=args.sh_degree)
    write_output(data, args.out)
    if args.out != "-":
        print(f"wrote {len(data)} bytes to {args.out}", file=sys.stderr)
    return 0
