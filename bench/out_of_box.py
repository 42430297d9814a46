"""The newcomer benchmark (issue 42): `flashmono serve` as a new user starts it, sessions created exactly as
openapi.yaml tells a mobile app (`skip_frames: true`, `frame_rate`, `intrinsics`; no preset, no tuning field), each
input mode streamed at a phone's 30 frames/s by a client that does not wait for poses.

Per case (sequence x input mode x size) it writes, as JSON under `bench/results/out_of_box/`: the share of frames
posed, pose latency (capture -> pose) p50/p95, `finish` time, ATE against the ground truth (SE(3); Sim(3) for RGB
only), PSNR of rendered non-keyframes, the worker's peak RSS, the settings the worker chose and why, the machine and
its load; with `--offline`, the offline `flashmono run` of the same frames (its defaults) beside it. Cases already
written are skipped (the run resumes after an interruption); `--force` runs them again.

`python -m bench out_of_box [--sequences icl tum] [--modes rgbd posed-rgbd posed-rgb rgb] [--sizes 320x240 640x480]
[--offline] [--force] [--frames N]`; a case run again without `--offline` keeps the offline figures it has.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.live import MODES, encode, load_frames, mode_inputs, run_offline, stream_case
from bench.record import commit, loadavg, machine

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results" / "out_of_box"
SEQUENCES = {
    "icl": [ROOT.parent / "shared" / "data" / "icl_livingroom1_micro", ROOT / "tests" / "data" / "icl_mini"],
    "tum": [ROOT.parent / "shared" / "data" / "tum_fr1_xyz"],
}
FPS = 30.0


class _Process:
    """A child process of `flashmono serve` (the Popen-like face bench.live's sampler reads)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid

    def poll(self) -> int | None:
        return None if Path(f"/proc/{self.pid}").exists() else 0


class ServeProcess:
    """`flashmono serve --ephemeral` on a free port, as a new user runs it; stopped on exit."""

    def __init__(self) -> None:
        from service.launcher import free_port

        self.port = free_port()
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.ws_url = f"ws://127.0.0.1:{self.port}"
        self.process: subprocess.Popen | None = None

    def __enter__(self) -> ServeProcess:
        import httpx

        command = [str(Path(sys.executable).with_name("flashmono")), "serve", "--port", str(self.port), "--ephemeral",
                   "--log-level", "warning"]
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.base_url}/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            if self.process.poll() is not None:
                raise RuntimeError("flashmono serve exited at start")
            time.sleep(0.5)
        raise RuntimeError("flashmono serve was not ready within 300 s")

    def __exit__(self, *exc: object) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()

    @property
    def gateway(self) -> _Process:
        return _Process(self.process.pid)  # uvicorn runs in the serve process itself

    @property
    def workers(self) -> list[_Process]:
        return [_Process(pid) for pid in _descendants(self.process.pid)
                if b"worker.runtime.main" in _cmdline(pid)]


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def case_args(mode: str, size: str, frames: int | None) -> argparse.Namespace:
    """The options bench.live's case runner reads: no preset (the session as documented), live skipping on."""
    return argparse.Namespace(mode=mode, size=size, fps=FPS, preset=None, every_frame=False, tracking_side=0,
                              kill_at=None, map_while_finishing=False, psnr_every=5, timeout_s=1800.0, frames=frames)


def run_case(stack: ServeProcess, source: Path, mode: str, size: str, frames_cap: int | None) -> dict[str, Any]:
    args = case_args(mode, size, frames_cap)
    width, height = (int(v) for v in size.split("x"))
    with_depth, with_pose = mode_inputs(mode)
    frames, intrinsics = load_frames(str(source), (width, height), frames_cap, with_depth=with_depth,
                                     with_pose=with_pose)
    messages = encode(frames, with_depth=with_depth, with_pose=with_pose)
    return live_figures(stack, frames, intrinsics, messages, args)


def live_figures(stack: ServeProcess, frames, intrinsics, messages: list[bytes], args: argparse.Namespace
                 ) -> dict[str, Any]:
    """One live case's figures: `messages` streamed by bench.live's paced client (`frames` hold the ground truth
    and the images PSNR is scored against, rendered with `intrinsics`)."""
    import httpx

    load_before = os.getloadavg()[0]
    result = asyncio.run(stream_case(stack, frames, intrinsics, messages, args))
    summary = result["summary"]
    session = httpx.get(f"{stack.base_url}/v1/sessions/{summary['session']}", timeout=30).json()
    return {
        "frames": summary["frames"], "posed_share": summary["with_pose"] / max(1, summary["frames"]),
        "skipped": summary["skipped"], "latency_p50_ms": summary["latency_ms"][50],
        "latency_p95_ms": summary["latency_ms"][95], "finish_s": summary["finish_s"], "ate_m": summary["ate_m"],
        "psnr_db": summary["psnr"], "rss_worker_peak_mib": summary["rss_worker_peak_mib"],
        # one server for every case: the worker holds up to 4 finished sessions' maps for renders, so its memory
        # at a case's start is not the bare process's
        "rss_worker_start_mib": result["samples"][0]["worker_rss"] if result["samples"] else None,
        "acked_lost": summary["acked_lost"], "loops": summary["loops"], "settings": session.get("settings"),
        "load": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }


def offline_case(source: Path, mode: str, size: str, frames_cap: int | None) -> dict[str, Any]:
    """The same frames through `flashmono run`'s engine with its defaults (no preset: the same decision)."""
    args = case_args(mode, size, frames_cap)
    width, height = (int(v) for v in size.split("x"))
    with tempfile.TemporaryDirectory(prefix="bench-oob-offline-") as out:
        return run_offline(str(source), (width, height), frames_cap, args, Path(out))


def _mib(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def table(folder: Path = OUT) -> str:
    """The results in `folder` as a markdown table (the README's live rows)."""
    rows = ["| sequence | input | size | posed | p50 / p95 (ms) | finish (s) | ATE live / offline (cm) | "
            "PSNR live / offline (dB) | worker RSS peak (at start) (MiB) | settings | load |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for path in sorted(folder.glob("*.json")):
        record = json.loads(path.read_text())
        live, offline = record["live"], record.get("offline") or {}
        settings = live.get("settings") or {}
        side = settings.get("working_side") or settings.get("tracking_side")

        def cm(value):
            return "-" if value is None else f"{100 * value:.2f}"

        def db(value):
            return "-" if value is None else f"{value:.2f}"

        rows.append(
            f"| {record['sequence']} | {record['mode']} | {record['size']} | {live['posed_share']:.1%} | "
            f"{live['latency_p50_ms']:.0f} / {live['latency_p95_ms']:.0f} | {live['finish_s']:.1f} | "
            f"{cm(live['ate_m'])} / {cm(offline.get('ate_m'))} | {db(live['psnr_db'])} / {db(offline.get('psnr'))} | "
            f"{live['rss_worker_peak_mib']:.0f} ({_mib(live.get('rss_worker_start_mib'))}) | {settings.get('preset')}"
            f"{f' at {side} px' if side else ''} | {live['load'][0]} -> {live['load'][1]} |")
    return "\n".join(rows)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench out_of_box", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", nargs="+", choices=sorted(SEQUENCES), default=["icl", "tum"])
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--sizes", nargs="+", default=["320x240", "640x480"])
    parser.add_argument("--frames", type=int, default=None, help="at most this many frames a case")
    parser.add_argument("--offline", action="store_true", help="also the offline run of the same frames")
    parser.add_argument("--force", action="store_true", help="run cases whose results exist again")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--table", action="store_true", help="print the results so far as a markdown table, run none")
    args = parser.parse_args(argv)
    if args.table:
        print(table(args.out))
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    cases = []
    for name in args.sequences:
        source = next((p for p in SEQUENCES[name] if p.is_dir()), None)
        if source is None:
            print(f"{name}: no sequence found ({', '.join(map(str, SEQUENCES[name]))}); skipped", flush=True)
            continue
        cases += [(name, source, mode, size) for size in args.sizes for mode in args.modes]
    todo = [c for c in cases if args.force or not (args.out / f"{c[0]}_{c[2]}_{c[3]}.json").exists()]
    print(f"{len(cases)} cases, {len(todo)} to run", flush=True)
    if not todo:
        return 0
    failed = 0
    with ServeProcess() as stack:
        for name, source, mode, size in todo:
            path = args.out / f"{name}_{mode}_{size}.json"
            started, load_start = time.monotonic(), loadavg()
            live = run_case(stack, source, mode, size, args.frames)
            # bench.scoreboard reads this file as two records (areas `live` and `offline`; its `expand`)
            record = {"benchmark": "out_of_box", "sequence": name, "source": source.name, "mode": mode,
                      "size": size, "fps": FPS, "commit": commit(), "machine": machine(),
                      "command": "python -m bench out_of_box " + " ".join(argv), "date": time.strftime("%F %T"),
                      "load": [load_start, loadavg()], "live": live}
            if args.offline:
                record["offline"] = offline_case(source, mode, size, args.frames)
            elif path.exists():  # a live case run again: the offline run of the same frames has not changed
                record["offline"] = json.loads(path.read_text()).get("offline")
            record["wall_s"] = round(time.monotonic() - started, 1)
            path.write_text(json.dumps(record, indent=1, default=str) + "\n")
            failed += live["acked_lost"] > 0
            print(f"{name} {mode} {size}: posed {live['posed_share']:.1%}, p95 {live['latency_p95_ms']:.0f} ms, "
                  f"finish {live['finish_s']:.1f} s, ATE {100 * (live['ate_m'] or float('nan')):.2f} cm, "
                  f"PSNR {live['psnr_db'] or float('nan'):.2f} dB, settings {live['settings']['preset']} "
                  f"(working side {live['settings'].get('working_side')}, tracking side "
                  f"{live['settings']['tracking_side']})", flush=True)
    return 1 if failed else 0
