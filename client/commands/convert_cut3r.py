"""`flashmono convert-cut3r IN.pth OUT.safetensors`: CUT3R-512 checkpoint -> our safetensors checkpoint."""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "convert-cut3r",
        help="convert a CUT3R 512 checkpoint (.pth) to a Flash-Mono frontend checkpoint (.safetensors)",
        description="Reads the .pth without executing pickle code (allow-listed globals only), maps CUT3R's keys to "
                    "the frontend model (the 2DGS head is freshly initialised) and writes safetensors.",
    )
    parser.add_argument("source", help="CUT3R checkpoint, e.g. cut3r_512_dpt_4_64.pth")
    parser.add_argument("target", help="output .safetensors path")
    parser.add_argument("--config", default="paper", help="frontend config whose shapes the checkpoint has")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from worker.frontend.cut3r_import import convert_cut3r_checkpoint

    try:
        fresh = convert_cut3r_checkpoint(args.source, args.target, args.config)
    except ValueError as exc:
        print(f"convert-cut3r: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {args.target} ({len(fresh)} freshly initialised tensors: 2DGS head adapter)")
    return 0
