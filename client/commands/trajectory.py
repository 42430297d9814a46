"""`flashmono trajectory ID`: a session's estimated trajectory as JSON or TUM text."""

from __future__ import annotations

import argparse
import json

from client.commands._options import add_server_options, make_client, reports_errors, write_output


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "trajectory", help="fetch a session's trajectory (JSON or TUM)",
        description="Fetch the camera-to-world trajectory of a session at its latest revision (loop closures "
                    "rewrite the past, so fetch again after one). JSON: {session_id, revision, which, poses: "
                    "[{seq, timestamp, pose: 16 row-major floats}]}; TUM: 'timestamp tx ty tz qx qy qz qw' lines.")
    parser.add_argument("session_id", metavar="ID", help="session id")
    add_server_options(parser)
    parser.add_argument("--format", choices=("json", "tum"), default="json", help="output format (default json)")
    parser.add_argument("--which", choices=("all", "keyframes"), default="all", help="every frame or keyframes only")
    parser.add_argument("--out", help="write to this file instead of stdout")
    parser.set_defaults(func=run)


@reports_errors
def run(args: argparse.Namespace) -> int:
    with make_client(args) as client:
        if args.format == "tum":
            text = client.trajectory_tum(args.session_id, args.which)
        else:
            trajectory = client.trajectory(args.session_id, args.which)
            text = json.dumps({
                "session_id": trajectory.session_id, "revision": trajectory.revision, "which": trajectory.which,
                "poses": [{"seq": p.seq, "timestamp": p.timestamp, "pose": p.pose.reshape(-1).tolist()}
                          for p in trajectory.poses],
            }, indent=1) + "\n"
    write_output(text, args.out)
    return 0
