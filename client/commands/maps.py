"""`flashmono maps`: saved maps on a server: list, show, save a session's, upload, download, delete."""

from __future__ import annotations

import argparse
import json
import sys

from client.commands._options import add_server_options, make_client, reports_errors, write_output
from client.rest import MAP_FILE_FORMATS

DESCRIPTION = """\
Saved maps: a finished session's map kept as a map of its own, to download, upload elsewhere, and start new
sessions in (`create_session(map_id=...)`).

  flashmono maps list
  flashmono maps show ID
  flashmono maps create --from-session SESSION --name NAME
  flashmono maps upload FILE [--name NAME]
  flashmono maps download ID --format package|ply|spz|splat --out PATH
  flashmono maps delete ID
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("maps", help="list, show, save, upload, download or delete saved maps",
                                   description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    listing = actions.add_parser("list", help="the maps this key may read, newest first")
    listing.add_argument("--limit", type=int, help="at most this many maps")
    listing.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    actions.add_parser("show", help="one map in full (JSON)").add_argument("map_id", metavar="ID")
    create = actions.add_parser("create", help="save a finished session's map")
    create.add_argument("--from-session", dest="session_id", metavar="SESSION", required=True,
                        help="a finished session this key created")
    create.add_argument("--name", required=True, help="the map's name")
    upload = actions.add_parser("upload", help="upload a map package (from `maps download --format package`)")
    upload.add_argument("file", metavar="FILE")
    upload.add_argument("--name", help="the map's name (default: the package's)")
    download = actions.add_parser("download", help="download a map's package or its surfels")
    download.add_argument("map_id", metavar="ID")
    download.add_argument("--format", choices=MAP_FILE_FORMATS, default="package",
                          help="package (to upload elsewhere) or the surfels as ply, spz or splat (default "
                               "%(default)s)")
    download.add_argument("--out", required=True, help="output file, '-' for stdout")
    download.add_argument("--version", type=int, help="a version of the map (default: the latest)")
    actions.add_parser("delete", help="delete a map and every version of it").add_argument("map_id", metavar="ID")
    for action in actions.choices.values():
        add_server_options(action)
    parser.set_defaults(func=run)


@reports_errors
def run(args: argparse.Namespace) -> int:
    with make_client(args) as client:
        if args.action == "list":
            return _list(client, args)
        if args.action == "show":
            print(json.dumps(client.get_map(args.map_id).raw, indent=2))
        elif args.action == "create":
            print(_line(client.create_map(args.session_id, args.name)))
        elif args.action == "upload":
            print(_line(client.upload_map(args.file, args.name)))
        elif args.action == "download":
            data = client.download_saved_map(args.map_id, args.format, version=args.version)
            write_output(data, args.out)
            if args.out != "-":
                print(f"wrote {len(data)} bytes ({args.format}) to {args.out}", file=sys.stderr)
        elif args.action == "delete":
            client.delete_map(args.map_id)
            print(f"deleted {args.map_id}")
    return 0


def _list(client, args: argparse.Namespace) -> int:
    if args.limit is not None and args.limit < 1:
        raise ValueError("--limit must be >= 1")
    maps = []
    for saved in client.iter_maps(page_size=min(args.limit or 100, 100)):
        maps.append(saved)
        if args.limit is not None and len(maps) >= args.limit:
            break
    if args.json:
        for saved in maps:
            print(json.dumps(saved.raw))
        return 0
    print(f"{'ID':<34} {'VER':>4} {'SURFELS':>9} {'KEYFR':>6} {'SCALE':<11} {'MB':>7} NAME")
    for saved in maps:
        print(_line(saved))
    return 0


def _line(saved) -> str:
    meta = saved.meta
    return (f"{saved.id:<34} {saved.latest_version:>4} {meta.get('surfels', 0):>9} {meta.get('keyframes', 0):>6} "
            f"{meta.get('scale', '-'):<11} {saved.size_bytes / 1e6:>7.2f} {saved.name or '-'}")
