"""`flashmono demo` end to end, as `make demo` runs it: embedded stack (serve), the bundled sequence streamed over
the WebSocket, ATE and PSNR printed, trajectory/map/renders written, viewer URL printed. The whole bundled sequence
with the defaults, exactly what the README's `make demo` runs: it revisits the room, so the loop-closure path
(pose graph + map correction) runs too; then the same frames without device poses (RGB-D odometry)."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_demo_runs_the_whole_system_and_writes_its_outputs(tmp_path: Path) -> None:
    out = tmp_path / "demo_out"
    env = {**os.environ, "FLASHMONO_TORCH_THREADS": "1"}
    env.pop("REDIS_URL", None)
    result = subprocess.run([sys.executable, "-m", "client.cli", "demo", "--out", str(out)], cwd=REPO_ROOT, env=env,
                            capture_output=True, text=True, timeout=600)
    log = (out / "serve.log").read_text() if (out / "serve.log").exists() else ""
    assert result.returncode == 0, f"{result.stdout}\n{result.stderr}\n{log[-3000:]}"

    metrics = json.loads((out / "metrics.json").read_text())
    frames = len(list((REPO_ROOT / "tests" / "data" / "icl_mini" / "rgb").iterdir()))
    assert metrics["frames"] == frames and metrics["poses"] == frames
    assert metrics["frame_errors"] == 0
    assert metrics["loop_closures"] >= 1, "the demo sequence revisits the room; no loop was closed"
    # the final refinement moved the keyframes' cameras, and the stream said so before `finished`
    assert metrics["poses_refined"] == 1
    assert math.isfinite(metrics["ate_rmse_m"]) and 0 <= metrics["ate_rmse_m"] < 0.5
    assert math.isfinite(metrics["psnr_db"]) and metrics["psnr_db"] > 10
    assert re.search(r"ATE RMSE\s+\d+\.\d+ cm", result.stdout)
    assert re.search(r"PSNR\s+\d+\.\d+ dB", result.stdout)
    assert re.search(rf"outputs\s+{re.escape(str(out.resolve()))}/ ", result.stdout), result.stdout
    viewer = re.search(r"viewer\s+(http://127\.0\.0\.1:\d+/viewer\?session=(\w+))", result.stdout)
    assert viewer and viewer.group(2) == metrics["session_id"]

    tum = [line for line in (out / "trajectory.tum").read_text().splitlines() if not line.startswith("#")]
    assert len(tum) == frames and all(len(line.split()) == 8 for line in tum)
    assert (out / "keyframes.tum").read_text().strip()
    truth = [line for line in (out / "groundtruth.tum").read_text().splitlines() if not line.startswith("#")]
    assert len(truth) == frames
    assert (out / "map.ply").read_bytes().startswith(b"ply\n")
    renders = sorted((out / "renders").glob("*.png"))
    assert len(renders) == 6  # the default --renders
    side_by_side = cv2.imread(str(renders[0]))
    assert side_by_side.shape == (240, 640, 3)  # rendered | captured, at the sequence's 320x240

    # The same frames without device poses (RGB-D odometry), reported beside the posed run.
    rgbd = json.loads((out / "rgbd" / "metrics.json").read_text())
    assert rgbd["mode"] == "rgbd" and rgbd["poses"] == frames and rgbd["frame_errors"] == 0
    assert rgbd["poses_refined"] == 1
    assert rgbd["session_id"] != metrics["session_id"]
    assert 0 <= rgbd["ate_rmse_m"] < 0.05, "RGB-D odometry on real frames should be centimetre-accurate"
    assert rgbd["psnr_db"] > 20
    assert re.search(r"^\s+rgbd\s+images \+ depth\s+\d+\.\d+\s+\d+\.\d+", result.stdout, re.M), result.stdout
