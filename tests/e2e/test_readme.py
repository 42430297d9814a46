"""The README's CLI and SDK examples, run verbatim against a real stack so they cannot rot."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
from live_stack import LiveStack

REPO_ROOT = Path(__file__).resolve().parents[2]


def _block(name: str) -> str:
    text = (REPO_ROOT / "README.md").read_text()
    match = re.search(rf"<!-- {name}:start -->\s*```\w+\n(.*?)```\s*<!-- {name}:end -->", text, re.DOTALL)
    assert match, f"README has no {name} block"
    return match.group(1)


def _workspace(tmp_path: Path) -> Path:
    (tmp_path / "tests" / "data").mkdir(parents=True)
    (tmp_path / "tests" / "data" / "icl_mini").symlink_to(REPO_ROOT / "tests" / "data" / "icl_mini")
    return tmp_path


def test_readme_cli_and_sdk_examples_run(tmp_path: Path) -> None:
    cli = _block("cli-example")
    sdk = _block("sdk-example")
    work = _workspace(tmp_path)
    # The commands and the SDK calls are under test; the passthrough engine keeps this test short on 2 cores.
    with LiveStack(workers=1, engine="passthrough") as stack:
        port = stack.url.rsplit(":", 1)[1]
        # The stack is already serving: drop the README's `flashmono serve` line, keep everything else verbatim.
        script = "\n".join(line for line in cli.splitlines() if not line.startswith("flashmono serve"))
        script = script.replace("127.0.0.1:8000", f"127.0.0.1:{port}")
        env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
        cli_run = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=work, env=env,
                                 capture_output=True, text=True, timeout=300)
        assert cli_run.returncode == 0, f"{cli_run.stdout}\n{cli_run.stderr}\n{stack.log_tail()}"
        assert "living-room" in cli_run.stdout  # the sessions listing
        tum = [line for line in (work / "trajectory.tum").read_text().splitlines() if not line.startswith("#")]
        assert len(tum) == 12
        assert cv2.imread(str(work / "view.png")).shape == (240, 320, 3)
        assert cv2.imread(str(work / "depth.png"), cv2.IMREAD_UNCHANGED).dtype == "uint16"
        assert (work / "map.ply").read_bytes().startswith(b"ply\n")

        sdk_run = subprocess.run([sys.executable, "-c", sdk.replace("127.0.0.1:8000", f"127.0.0.1:{port}")],
                                 cwd=work, env={**env, "PYTHONPATH": str(REPO_ROOT)}, capture_output=True,
                                 text=True, timeout=300)
        assert sdk_run.returncode == 0, f"{sdk_run.stdout}\n{sdk_run.stderr}\n{stack.log_tail()}"
        assert re.search(r"8 frames, 8 poses, \(240, 320, 3\), map \d+ bytes", sdk_run.stdout), sdk_run.stdout
