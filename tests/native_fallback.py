"""Run a Python snippet in a fresh interpreter where no compiled kernel can build (CXX=false, an empty extension
cache), so the kernels' reference fallbacks are what runs: the oracle tests of every compiled module use it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_without_compiler(script: str, ext_dir: Path, timeout_s: float = 120) -> subprocess.CompletedProcess:
    """`script` run from the repository root with the C++ compiler disabled; fails the test when it exits non-zero."""
    env = dict(os.environ, CXX="false", FLASHMONO_EXT_DIR=str(ext_dir))
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=timeout_s)
    assert result.returncode == 0, result.stderr
    return result
