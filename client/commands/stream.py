"""`flashmono stream SOURCE`: stream a video, image folder, dataset or webcam into a session, like a phone."""

from __future__ import annotations

import argparse
import sys

from client.commands._options import add_server_options, make_client, parse_size, reports_errors

DESCRIPTION = """\
Stream frames to a Flash-Mono server over its WebSocket, exactly as a phone app does (JPEG frames, optional
intrinsics, depth and device poses), and print the live tracking summary.

SOURCE is a video file, a folder of images, a dataset folder (TUM, ICL, Replica, ScanNet, KITTI), a URI such as
synthetic://seed=3?frames=60, or webcam:N for camera N. A new session is created unless --session is given.
The client keeps a small window of unacknowledged frames and slows down when the server's queue fills
(backpressure); no frame is silently dropped.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("stream", help="stream a video/folder/dataset/webcam to a server",
                                   description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="video file, image folder, dataset folder, synthetic:// URI or webcam:N")
    add_server_options(parser)
    parser.add_argument("--session", help="stream into this existing session instead of creating one")
    parser.add_argument("--name", help="name of the new session")
    parser.add_argument("--preset", help="SLAM preset of the new session (omitted: the server chooses from the input "
                                         "and its machine, `auto`)")
    parser.add_argument("--device-id", help="device id recorded with the new session")
    parser.add_argument("--fps", type=float, help="pace frames like a live camera at this rate (default: as fast "
                                                  "as the server takes them)")
    parser.add_argument("--skip-frames", choices=("auto", "on", "off"), default="auto",
                        help="let the tracker skip frames that fell behind a newer one (a live camera) or track "
                             "every frame however late (recorded data); auto: on for webcam:N and with --fps")
    parser.add_argument("--stride", type=int, default=1, help="use every STRIDE-th frame")
    parser.add_argument("--max-frames", type=int, help="stop after this many frames")
    parser.add_argument("--resize", type=parse_size, metavar="WxH", help="resize frames (intrinsics follow)")
    parser.add_argument("--camera", metavar="JSON", help="the camera's calibration, a JSON file {fx, fy, cx, cy, "
                                                         "width, height, distortion?} (distortion as openapi.yaml's "
                                                         "DistortionIn, e.g. {\"model\": \"radtan\", \"k1\": "
                                                         "0.1, ...}): the new session's intrinsics, the frames sent "
                                                         "as the camera took them (a webcam's raw images)")
    parser.add_argument("--send-depth", action="store_true", help="send the source's depth maps (RGB-D mode)")
    parser.add_argument("--send-pose", action="store_true", help="send the source's poses (posed mode)")
    parser.add_argument("--jpeg-quality", type=int, default=90, help="JPEG quality 1..100 (default %(default)s)")
    parser.add_argument("--window", type=int, default=4, help="max frames sent but not yet acknowledged")
    parser.add_argument("--max-pending", type=int, default=8, help="max frames queued at the server")
    parser.add_argument("--tum-out", help="write the final trajectory (TUM text) to this file")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


@reports_errors
def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from client.streaming import WireOptions, open_frames

    source_options = {}
    if args.send_depth:
        source_options["use_gt_depth"] = True
    if args.send_pose:
        source_options["use_gt_poses"] = True
    frames = open_frames(args.source, stride=args.stride, max_frames=args.max_frames, resize=args.resize,
                         **source_options)
    total = _length(frames)
    camera = _camera(args.camera) if args.camera else None
    with make_client(args) as client:
        session_id = args.session
        if session_id is None:
            session = client.create_session(intrinsics=camera or getattr(frames, "intrinsics", None),
                                            preset=args.preset,
                                            name=args.name, device_id=args.device_id,
                                            skip_frames=_skips_frames(args), frame_rate=args.fps)
            session_id = session.id
        print(f"session {session_id}", file=sys.stderr)
        bar = tqdm(total=total, unit="frame", desc="tracked", disable=args.quiet, file=sys.stderr)
        loops = 0

        def on_event(event: object) -> None:
            nonlocal loops
            from client.models import LoopClosedEvent

            if isinstance(event, LoopClosedEvent):
                loops += 1
                bar.set_postfix(loops=loops)
            else:
                bar.update(1)

        wire = WireOptions(jpeg_quality=args.jpeg_quality, send_depth=args.send_depth, send_pose=args.send_pose,
                           send_intrinsics=camera is None)
        try:
            summary = client.stream(session_id, frames, on_event=on_event, fps=args.fps, window=args.window,
                                    max_pending=args.max_pending, wire=wire)
        finally:
            bar.close()
        print(f"sent {summary.frames_sent} frames, {len(summary.poses)} poses, {len(summary.loop_closures)} loop "
              f"closures, {summary.backpressure_retries} re-sent after backpressure, {len(summary.errors)} errors, "
              f"{summary.fps:.1f} frames/s")
        for error in summary.errors:
            print(f"  frame error: {error.get('code')}: {error.get('message')} (seq {error.get('seq')})",
                  file=sys.stderr)
        if args.tum_out:
            with open(args.tum_out, "w") as f:
                f.write(client.trajectory_tum(session_id))
            print(f"trajectory written to {args.tum_out}")
        print(session_id)
    return 0


def _camera(path: str) -> dict:
    """The calibration file's intrinsics (checked by the server when the session is created)."""
    import json

    try:
        camera = json.loads(open(path).read())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"--camera {path}: {err}") from err
    if not isinstance(camera, dict):
        raise ValueError(f"--camera {path}: expected an object {{fx, fy, cx, cy, width, height, distortion?}}")
    return camera


def _length(frames: object) -> int | None:
    try:
        return len(frames)  # type: ignore[arg-type]
    except TypeError:
        return None


def _skips_frames(args: argparse.Namespace) -> bool:
    """Whether the new session may skip late frames: asked for, or a live source (a webcam, paced frames)."""
    if args.skip_frames != "auto":
        return args.skip_frames == "on"
    return str(args.source).startswith("webcam:") or args.fps is not None
