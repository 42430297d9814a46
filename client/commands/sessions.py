"""`flashmono sessions`: list sessions on a server (fleet view), show or delete one."""

from __future__ import annotations

import argparse
import json

from client.commands._options import add_server_options, make_client, reports_errors

DESCRIPTION = """\
List the sessions of a Flash-Mono server, newest first, filtered by status, device or name; all pages are
followed unless --limit is given. With --show ID print one session in full (JSON); with --delete ID delete it.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sessions", help="list, show or delete sessions on a server",
                                   description=DESCRIPTION)
    add_server_options(parser)
    parser.add_argument("--status", help="only sessions in this status (created, streaming, finishing, finished, "
                                         "failed)")
    parser.add_argument("--device-id", help="only sessions of this device")
    parser.add_argument("--name", help="only sessions with this name")
    parser.add_argument("--limit", type=int, help="at most this many sessions")
    parser.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    action = parser.add_mutually_exclusive_group()
    action.add_argument("--show", metavar="ID", help="print this session in full")
    action.add_argument("--delete", metavar="ID", help="delete this session")
    parser.set_defaults(func=run)


@reports_errors
def run(args: argparse.Namespace) -> int:
    with make_client(args) as client:
        if args.show:
            print(json.dumps(client.get_session(args.show).raw, indent=2, default=str))
            return 0
        if args.delete:
            client.delete_session(args.delete)
            print(f"deleted {args.delete}")
            return 0
        if args.limit is not None and args.limit < 1:
            raise ValueError("--limit must be >= 1")
        filters = {"status": args.status, "device_id": args.device_id, "name": args.name}
        sessions = []
        for session in client.iter_sessions(page_size=min(args.limit or 100, 100), **filters):
            sessions.append(session)
            if args.limit is not None and len(sessions) >= args.limit:
                break
    if args.json:
        for session in sessions:
            print(json.dumps(session.raw, default=str))
        return 0
    header = f"{'ID':<34} {'STATUS':<10} {'FRAMES':>7} {'KEYFR':>6} {'REV':>4} {'DEVICE':<14} NAME"
    print(header)
    for s in sessions:
        print(f"{s.id:<34} {s.status:<10} {s.frames_processed:>7} {s.keyframes:>6} {s.revision:>4} "
              f"{(s.device_id or '-'):<14} {s.name or '-'}")
    return 0
