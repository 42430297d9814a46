"""`flashmono eval SOURCES... --out DIR`: run several sequences and print tables shaped like the paper's
Tables 1 (ATE), 2 (PSNR/SSIM/LPIPS, FPS) and 5 (depth L1). Each sequence's files go to DIR/<name>/."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from client.commands.run import add_run_options, run_one


def _eval(args: argparse.Namespace) -> int:
    from worker.data import DatasetError
    from worker.eval import all_tables

    rows = []
    names: set[str] = set()
    for source in args.sources:
        name = Path(str(source).rstrip("/")).name or "sequence"
        while name in names:
            name += "_"
        names.add(name)
        try:
            rows.append(run_one(args, source, str(Path(args.out) / name)))
        except (ValueError, DatasetError) as err:
            print(f"error: {source}: {err}", file=sys.stderr)
            return 2
        rows[-1]["sequence"] = name
    tables = all_tables(rows, ate_unit=args.ate_unit)
    (Path(args.out) / "tables.md").write_text(tables)
    print(tables)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval", help="run several sequences and print the paper's tables",
                                   description=__doc__)
    parser.add_argument("sources", nargs="+", help="dataset folders / videos / synthetic:// URIs")
    parser.add_argument("--ate-unit", default="cm", choices=["cm", "m", "mm"], help="unit of Table 1")
    add_run_options(parser)
    parser.set_defaults(func=_eval)
