"""The gateway image (docker/Dockerfile.gateway) installs docker/requirements-gateway.txt and the code with
--no-deps: those requirements must be enough to serve, and must leave torch and the engine's libraries out."""

from __future__ import annotations

import importlib.metadata
import os
import re
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
REQUIREMENTS = ROOT / "docker" / "requirements-gateway.txt"


def _names(specs: list[str]) -> set[str]:
    return {re.split(r"[\[<>=!~ ]", spec, maxsplit=1)[0].lower() for spec in specs}


def _gateway_requirements() -> list[str]:
    return [line.split("#")[0].strip() for line in REQUIREMENTS.read_text().splitlines()
            if line.split("#")[0].strip()]


def _engine_only_modules() -> set[str]:
    """Top-level modules of the distribution's dependencies the gateway image does not install."""
    dependencies = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    left_out = _names(dependencies) - _names(_gateway_requirements())
    modules = set()
    for module, distributions in importlib.metadata.packages_distributions().items():
        if any(d.lower().replace("_", "-") in left_out for d in distributions):
            modules.add(module)
    return modules


def test_gateway_requirements_are_the_distributions_own_without_torch():
    dependencies = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    requirements = _gateway_requirements()
    assert set(requirements) <= set(dependencies), sorted(set(requirements) - set(dependencies))
    assert not _names(requirements) & {"torch", "gtsam", "kornia", "opencv-python-headless", "roma"}
    text = (ROOT / "docker" / "Dockerfile.gateway").read_text()
    assert "pip install -r docker/requirements-gateway.txt" in text and "pip install --no-deps ." in text
    installs = re.findall(r"pip install .*", text)
    assert installs and not any("torch" in line for line in installs), installs


def test_the_gateway_serves_with_the_engine_libraries_missing():
    blocked = sorted(_engine_only_modules())
    assert {"torch", "cv2", "gtsam"} <= set(blocked)
    script = textwrap.dedent(f"""
        import importlib.abc
        import sys

        BLOCKED = set({blocked!r})

        class Missing(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ModuleNotFoundError(f"No module named {{name!r}} (not in the gateway image)")
                return None

        sys.meta_path.insert(0, Missing())
        from client.cli import build_parser
        from service.app import create_app
        from service.settings import Settings

        args = build_parser().parse_args(["serve", "--host", "0.0.0.0", "--port", "8000", "--workers", "0"])
        assert args.command == "serve"
        schema = create_app(Settings(api_keys={{"k": frozenset({{"admin"}})}})).openapi()
        assert "x-websocket" in schema
        import client.commands.serve, service.redis_embedded, worker.runtime.migrate  # noqa: E401
        print("ok")
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stdout + result.stderr
