"""`flashmono render ID --pose ...`: render a session's map from any camera pose to a PNG."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from client.commands._options import add_server_options, make_client, reports_errors, write_output

DESCRIPTION = """\
Render the session's surfel map from a camera pose. --pose is 16 comma-separated floats (camera-to-world,
row-major), or 'last' (the newest tracked pose) or 'seq:N' (the pose of frame N). The camera defaults to the
session's intrinsics; override with --width/--height/--fx/--fy/--cx/--cy. --kind depth gives a 16-bit PNG in mm.
--as-captured (with 'last' or 'seq:N') renders the colours under the exposure the camera had at that frame, as its
photo shows them, instead of the map's exposure-normalised colours.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("render", help="render a view of a session's map to PNG",
                                   description=DESCRIPTION)
    parser.add_argument("session_id", metavar="ID", help="session id")
    add_server_options(parser)
    parser.add_argument("--pose", required=True, help="16 comma-separated floats, 'last' or 'seq:N'")
    parser.add_argument("--kind", choices=("color", "depth"), default="color", help="colour or depth image")
    parser.add_argument("--as-captured", action="store_true",
                        help="colours under the exposure of the frame --pose names ('last' or 'seq:N')")
    for name in ("width", "height"):
        parser.add_argument(f"--{name}", type=int, help=f"image {name} (default: the session's)")
    for name in ("fx", "fy", "cx", "cy"):
        parser.add_argument(f"--{name}", type=float, help=f"intrinsic {name} (default: the session's)")
    parser.add_argument("--out", default="render.png", help="output PNG, '-' for stdout (default %(default)s)")
    parser.set_defaults(func=run)


def parse_pose_values(text: str) -> list[float]:
    """16 floats from 'a,b,c,...' (spaces allowed)."""
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    try:
        values = [float(p) for p in parts]
    except ValueError as err:
        raise ValueError(f"--pose must be 16 comma-separated numbers, 'last' or 'seq:N': {err}") from err
    if len(values) != 16:
        raise ValueError(f"--pose needs 16 numbers (a 4x4 camera-to-world matrix), got {len(values)}")
    return values


def resolve_pose(client: Any, session_id: str, text: str) -> tuple[Any, int | None]:
    """(the pose --pose names, the seq of its frame or None for a pose given as numbers)."""
    if text == "last" or text.startswith("seq:"):
        poses = client.trajectory(session_id).poses
        if not poses:
            raise ValueError("the session has no tracked poses yet")
        if text == "last":
            return poses[-1].pose, poses[-1].seq
        wanted = int(text[4:])
        for p in poses:
            if p.seq == wanted:
                return p.pose, p.seq
        raise ValueError(f"no pose for frame seq {wanted}")
    return parse_pose_values(text), None


def resolve_camera(args: argparse.Namespace, session_intrinsics: dict[str, Any] | None) -> dict[str, Any]:
    known = dict(session_intrinsics or {})
    camera = {}
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        value = getattr(args, key)
        camera[key] = value if value is not None else known.get(key)
    missing = [k for k, v in camera.items() if v is None]
    if missing:
        raise ValueError(f"the session has no intrinsics for {missing}; pass --{' --'.join(missing)}")
    return camera


@reports_errors
def run(args: argparse.Namespace) -> int:
    with make_client(args) as client:
        pose, seq = resolve_pose(client, args.session_id, args.pose)
        if args.as_captured and seq is None:
            raise ValueError("--as-captured needs --pose 'last' or 'seq:N' (a frame whose exposure to use)")
        needs_session = any(getattr(args, k) is None for k in ("width", "height", "fx", "fy", "cx", "cy"))
        intrinsics = client.get_session(args.session_id).intrinsics if needs_session else None
        png = client.render(args.session_id, pose, kind=args.kind, exposure_of=seq if args.as_captured else None,
                            **resolve_camera(args, intrinsics))
    write_output(png, args.out)
    if args.out != "-":
        print(f"wrote {args.out}", file=sys.stderr)
    return 0
