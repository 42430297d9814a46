"""`flashmono demo`: the main job on a fresh machine.

Starts the embedded stack (`flashmono serve`: gateway, a worker, private Redis), streams the bundled demo sequence
through the WebSocket exactly as a phone does, then prints the trajectory error (ATE after Sim(3) alignment) and
the rendering quality (PSNR of views rendered at the estimated poses), writes trajectory, map and rendered images
to --out, and prints the viewer URL.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
BUNDLED_SEQUENCE = REPO_ROOT / "tests" / "data" / "icl_mini"
SYNTHETIC_FALLBACK = "synthetic://seed=10001?frames=40&width=320&height=240"

DESCRIPTION = """\
Run Flash-Mono end to end on the bundled demo sequence (ICL-NUIM living room, 320x240; a synthetic room when the
repository's test data is absent): start the embedded stack, stream the frames over the WebSocket like a phone,
and report ATE (m, after Sim(3) alignment to ground truth) and PSNR (dB, views rendered at the estimated poses).
Outputs in --out: trajectory.tum, keyframes.tum, groundtruth.tum, map.ply, renders/*.png (rendered | captured),
metrics.json. --server uses a running server instead of starting one.
"""

MODES = {
    # mode: (send depth, send device poses)
    "mono": (False, False),
    "rgbd": (True, False),
    "posed": (True, True),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the whole system on the bundled demo sequence",
                                   description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", default=None, help="sequence to stream (default: the bundled ICL subset)")
    parser.add_argument("--out", default="demo_out", help="output folder (default %(default)s)")
    # By default a phone with device poses and LiDAR ("posed"), then the same frames without the poses ("rgbd":
    # tracked by RGB-D odometry), so both input modes are measured on real images in one run.
    parser.add_argument("--mode", choices=sorted(MODES), nargs="+", default=["posed", "rgbd"],
                        help="what the 'phone' sends, one run each: mono (images), rgbd (+ depth, as LiDAR phones "
                             "that send no poses), posed (+ depth and device poses); default: posed rgbd. The "
                             "first mode's outputs go in --out, the others' in --out/<mode>/")
    parser.add_argument("--preset", default=None,
                        help="SLAM preset (default: none, as a new user's session: the server chooses from the input "
                             "and its machine; 'fast' is quicker with a coarser map)")
    parser.add_argument("--max-frames", type=int, default=None, help="stream at most this many frames")
    parser.add_argument("--renders", type=int, default=6, help="how many views to render for PSNR (default 6)")
    parser.add_argument("--server", default=None, help="use this running server instead of starting one")
    parser.add_argument("--api-key", default=os.environ.get("FLASHMONO_API_KEY"), help="API key for --server")
    parser.add_argument("--port", type=int, default=0, help="port of the embedded gateway (default: a free one)")
    parser.add_argument("--keep-serving", action="store_true",
                        help="keep the embedded server (and the viewer) running until Ctrl-C")
    parser.set_defaults(func=run)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class EmbeddedStack:
    """`flashmono serve` in a child process (gateway + 1 worker + private Redis), stopped on exit."""

    def __init__(self, port: int, log_path: Path) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path
        self.process: subprocess.Popen | None = None

    def __enter__(self) -> EmbeddedStack:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        env.pop("REDIS_URL", None)  # always the private Redis
        env.pop("FLASHMONO_API_KEYS", None)
        env.pop("FLASHMONO_API_KEYS_FILE", None)
        self.log = open(self.log_path, "w")
        # A process group of its own, so that the workers `serve` starts can be ended with it (see __exit__).
        self.process = subprocess.Popen(
            [sys.executable, "-m", "client.cli", "serve", "--host", "127.0.0.1", "--port", str(self.port),
             "--workers", "1", "--ephemeral"], stdout=self.log, stderr=subprocess.STDOUT, env=env, cwd=REPO_ROOT,
            start_new_session=True)
        return self

    def wait_ready(self, client: Any, timeout_s: float = 600.0) -> None:
        from client.errors import FlashMonoError

        deadline = time.monotonic() + timeout_s
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"flashmono serve exited with {self.process.returncode}; see {self.log_path}")
            try:
                client.ready()
                return
            except FlashMonoError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"not ready after {timeout_s:.0f} s; see {self.log_path}") from None
                time.sleep(0.5)

    def __exit__(self, *exc: Any) -> None:
        if self.process is not None:
            if self.process.poll() is None:
                self.process.terminate()  # serve stops its workers and Redis
                try:
                    self.process.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    pass
            try:  # whatever of the group outlived serve (a worker stuck in a long step) ends now
                os.killpg(self.process.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            if self.process.poll() is None:
                self.process.wait()
        self.log.close()


def run(args: argparse.Namespace) -> int:
    # SIGTERM (e.g. from `timeout`) unwinds like Ctrl-C, so the embedded stack is always stopped.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    source = args.source or (str(BUNDLED_SEQUENCE) if BUNDLED_SEQUENCE.is_dir() else SYNTHETIC_FALLBACK)
    if args.server:
        return run_modes(args.server, args.api_key, source, args, out)
    print("starting the embedded stack (gateway + worker + Redis)...", file=sys.stderr)
    with EmbeddedStack(args.port, out / "serve.log") as stack:
        from client.sdk import FlashMonoClient

        with FlashMonoClient(stack.url) as client:
            try:
                stack.wait_ready(client)
            except RuntimeError as err:
                print(f"error: {err}", file=sys.stderr)
                return 1
        status = run_modes(stack.url, None, source, args, out)
        if status == 0 and args.keep_serving:
            print("serving; press Ctrl-C to stop", file=sys.stderr)
            try:
                while stack.process.poll() is None:
                    time.sleep(1)
            except KeyboardInterrupt:
                pass
        return status


def run_modes(server: str, api_key: str | None, source: str, args: argparse.Namespace, out: Path) -> int:
    """One streamed session per --mode (the first one's outputs in `out`, the others' in out/<mode>/), then the
    figures of all of them side by side."""
    modes = list(dict.fromkeys(args.mode))
    status, results = 0, []
    for k, mode in enumerate(modes):
        mode_out = out if k == 0 else out / mode
        mode_out.mkdir(parents=True, exist_ok=True)
        code, metrics = run_demo(server, api_key, source, mode, args, mode_out)
        status |= code
        if metrics is None:
            break
        results.append(metrics)
        print_report(metrics, mode_out, f"{server.rstrip('/')}/viewer?session={metrics['session_id']}")
    if len(results) > 1:
        print_comparison(results)
    return status


def run_demo(server: str, api_key: str | None, source: str, mode: str, args: argparse.Namespace, out: Path
             ) -> tuple[int, dict[str, Any] | None]:
    """Stream `source` in `mode` to a new session and evaluate it: (exit status, metrics or None)."""
    from tqdm import tqdm

    from client.errors import FlashMonoError
    from client.models import PoseEvent
    from client.sdk import FlashMonoClient
    from client.streaming import WireOptions, open_frames

    send_depth, send_pose = MODES[mode]
    frames = list(open_frames(source, max_frames=args.max_frames, use_gt_poses=send_pose))
    if not frames:
        print(f"error: {source} has no frames", file=sys.stderr)
        return 1, None
    intrinsics = frames[0].intrinsics
    started = time.monotonic()
    try:
        with FlashMonoClient(server, api_key=api_key) as client:
            session = client.create_session(intrinsics=intrinsics, preset=args.preset, name="demo",
                                            device_id="flashmono-demo", skip_frames=False,
                                            metadata={"source": Path(source).name, "mode": mode})
            print(f"session {session.id}: streaming {len(frames)} frames ({mode}) from {source}",
                  file=sys.stderr)
            with tqdm(total=len(frames), unit="frame", desc="tracked", file=sys.stderr) as bar:
                summary = client.stream(
                    session.id, frames, wire=WireOptions(send_depth=send_depth, send_pose=send_pose),
                    on_event=lambda e: bar.update(1) if isinstance(e, PoseEvent) else None)
            elapsed = time.monotonic() - started
            session = client.get_session(session.id)
            trajectory = client.trajectory(session.id)
            (out / "trajectory.tum").write_text(client.trajectory_tum(session.id))
            (out / "keyframes.tum").write_text(client.trajectory_tum(session.id, "keyframes"))
            keyframe_seqs = {p.seq for p in client.trajectory(session.id, "keyframes").poses}
            metrics = evaluate(client, session.id, trajectory, keyframe_seqs, frames, args.renders, out)
            try:
                map_bytes = client.download_map(session.id)
                (out / "map.ply").write_bytes(map_bytes)
            except FlashMonoError as err:
                map_bytes = b""
                metrics["map_error"] = str(err)
                print(f"warning: map export failed: {err}", file=sys.stderr)
    except FlashMonoError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1, None
    metrics.update({
        "session_id": session.id, "source": source, "mode": mode, "preset": session.preset,
        "settings": session.settings,
        "frames": len(frames), "poses": len(trajectory.poses), "keyframes": len(keyframe_seqs),
        "loop_closures": len(summary.loop_closures), "backpressure_retries": summary.backpressure_retries,
        "poses_refined": sum(e.kind == "poses_refined" for e in summary.tracking_events),
        "frame_errors": len(summary.errors), "end_to_end_fps": len(frames) / elapsed, "map_bytes": len(map_bytes),
    })
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return (1 if "render_error" in metrics or "map_error" in metrics else 0), metrics


def evaluate(client: Any, session_id: str, trajectory: Any, keyframe_seqs: set[int], frames: list,
             renders: int, out: Path) -> dict[str, Any]:
    """ATE against the frames' ground truth (matched by timestamp) and PSNR of renders at estimated poses."""
    import cv2
    import numpy as np

    from worker.data.tum_trajectory import Trajectory, format_tum
    from worker.eval.metrics import ate_rmse, psnr

    by_time = {round(f.timestamp, 6): f for f in frames}
    matched = [(p, by_time.get(round(p.timestamp, 6))) for p in trajectory.poses]
    matched = [(p, f) for p, f in matched if f is not None]
    metrics: dict[str, Any] = {"ate_rmse_m": None, "psnr_db": None}
    with_gt = [(p, f) for p, f in matched if f.gt_pose is not None]
    if len(with_gt) >= 3:
        estimated = np.stack([p.pose for p, _ in with_gt])
        truth = np.stack([np.asarray(f.gt_pose, dtype=np.float64) for _, f in with_gt])
        timestamps = np.array([p.timestamp for p, _ in with_gt])
        metrics["ate_rmse_m"] = ate_rmse(estimated, truth, align="sim3")
        (out / "groundtruth.tum").write_text(format_tum(Trajectory(timestamps, truth)))
    # Render preferably at non-keyframes (views the map was not refined on), spread over the sequence.
    candidates = [(p, f) for p, f in matched if p.seq not in keyframe_seqs] or matched
    picks = [candidates[i] for i in np.linspace(0, len(candidates) - 1, min(renders, len(candidates))).astype(int)]
    render_dir = out / "renders"
    render_dir.mkdir(exist_ok=True)
    values = []
    from client.errors import FlashMonoError

    for pose, frame in picks:
        k = frame.intrinsics
        try:
            rendered = client.render_array(session_id, pose.pose, width=k.width, height=k.height, fx=k.fx,
                                           fy=k.fy, cx=k.cx, cy=k.cy)
        except FlashMonoError as err:  # report what was measured and why the rest is missing
            metrics["render_error"] = str(err)
            print(f"warning: rendering failed: {err}", file=sys.stderr)
            break
        values.append(psnr(rendered, frame.image))
        side_by_side = np.concatenate([rendered, frame.image], axis=1)
        cv2.imwrite(str(render_dir / f"frame_{pose.seq:05d}.png"), cv2.cvtColor(side_by_side, cv2.COLOR_RGB2BGR))
    if values:
        metrics["psnr_db"] = float(np.mean(values))
        metrics["psnr_per_view_db"] = [float(v) for v in values]
    return metrics


def print_report(metrics: dict[str, Any], out: Path, viewer_url: str) -> None:
    ate = metrics.get("ate_rmse_m")
    psnr_db = metrics.get("psnr_db")
    print()
    print("Flash-Mono demo")
    print(f"  sequence        {metrics['source']} ({metrics['frames']} frames, mode {metrics['mode']}, "
          f"preset {metrics['preset']})")
    print(f"  tracked         {metrics['poses']} poses, {metrics['keyframes']} keyframes, "
          f"{metrics['loop_closures']} loop closures")
    print(f"  ATE RMSE        {ate * 100:.2f} cm (Sim(3)-aligned)" if ate is not None else "  ATE RMSE        n/a")
    print(f"  PSNR            {psnr_db:.2f} dB (renders at estimated poses)" if psnr_db is not None
          else "  PSNR            n/a")
    print(f"  end-to-end      {metrics['end_to_end_fps']:.2f} frames/s")
    print(f"  outputs         {out.resolve()}/ (trajectory.tum, keyframes.tum, groundtruth.tum, map.ply, renders/, "
          "metrics.json)")
    print(f"  viewer          {viewer_url}")


def print_comparison(results: list[dict[str, Any]]) -> None:
    """The modes' figures side by side."""
    print()
    print("  mode     sends                             ATE (cm)   PSNR (dB)   frames/s")
    for m in results:
        depth, pose = MODES[m["mode"]]
        sends = "images" + (" + depth" if depth else "") + (" + device poses" if pose else "")
        ate = "n/a" if m.get("ate_rmse_m") is None else f"{m['ate_rmse_m'] * 100:.2f}"
        psnr_db = "n/a" if m.get("psnr_db") is None else f"{m['psnr_db']:.2f}"
        print(f"  {m['mode']:<8} {sends:<33} {ate:>8}   {psnr_db:>9}   {m['end_to_end_fps']:>8.2f}")
