"""Tracking's cost per frame with mapping beside it, in a thread and in a process of its own (issue 42 point 2).

Each case runs `flashmono run` on a sequence three ways, in turn, on the same machine: tracking alone (mapping
disabled), mapping in a thread of the session's process, mapping in a process of its own (`mapping.process`). Per
run: tracking's wall time per frame (`frontend_tracking` of the runtime breakdown), frames tracked per second while
streaming (`fps_streaming`: the pace a live stream could be served at), the run's wall time, ATE and held-out PSNR.
Offline runs wait for mapping (it sheds nothing), so the map is the same three ways up to thread timing; what
changes is how much tracking pays for sharing the machine with it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.record import ROOT, Recorder

SHARED = ROOT.parent / "shared" / "data"
SEQUENCES = {"icl": SHARED / "icl_livingroom1_micro", "tum": SHARED / "tum_fr1_xyz"}
MODES = {"rgbd": ["--use-gt-depth"], "rgb": [], "posed-rgb": ["--use-gt-poses"]}
VARIANTS = {"tracking_alone": {"mapping": {"enabled": False}}, "thread": {"mapping": {"process": False}},
            "process": {"mapping": {"process": True}}}


def run_once(source: Path, mode: str, variant: str, max_frames: int | None) -> dict[str, Any]:
    """One `flashmono run` of `source` in `mode` with `variant`'s mapping; its figures."""
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "config.json"
        config.write_text(json.dumps(VARIANTS[variant]))
        command = [sys.executable, "-m", "client.cli", "run", str(source), "--out", str(Path(tmp) / "out"),
                   "--config", str(config), "--no-progress", *MODES[mode]]
        if max_frames:
            command += ["--max-frames", str(max_frames)]
        started = time.monotonic()
        subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
        wall = time.monotonic() - started
        metrics = json.loads((Path(tmp) / "out" / "metrics.json").read_text())
    breakdown = metrics["runtime_breakdown"]
    tracking = breakdown["frontend_tracking"]["ms_per_frame"] + breakdown["frontend_inference"]["ms_per_frame"]
    return {"tracking_ms_per_frame": tracking, "fps_streaming": metrics.get("fps_streaming"),
            "wall_s": round(wall, 1), "ate_m": metrics.get("ate_rmse"), "psnr_db": metrics.get("psnr"),
            "frames": metrics.get("num_frames") or metrics.get("frames")}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench mapping_process", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", nargs="+", choices=sorted(SEQUENCES), default=["icl"])
    parser.add_argument("--modes", nargs="+", choices=sorted(MODES), default=["rgbd", "rgb"])
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--max-frames", type=int, default=None)
    args = parser.parse_args(argv)
    recorder = Recorder("mapping_process", argv)
    for name in args.sequences:
        source = SEQUENCES[name]
        if not source.exists():
            print(f"{name}: {source} not found, skipped", flush=True)
            continue
        for mode in args.modes:
            figures = {variant: run_once(source, mode, variant, args.max_frames) for variant in args.variants}
            for variant, values in figures.items():
                recorder.write({"area": "mapping_process", "sequence": source.name, "mode": mode,
                                "variant": variant}, values)
            print(f"{name} {mode}: " + " | ".join(
                f"{v}: tracking {f['tracking_ms_per_frame']:.1f} ms/frame, {f['fps_streaming']:.1f} fps streaming, "
                f"wall {f['wall_s']:.0f} s" + (f", ATE {100 * f['ate_m']:.2f} cm, {f['psnr_db']:.2f} dB"
                                                if f["psnr_db"] is not None else "")
                for v, f in figures.items()), flush=True)
    return 0
