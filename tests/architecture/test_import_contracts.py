"""The import contracts of pyproject.toml ([tool.importlinter]) hold, and would fail if broken; the gateway and the
SDK load and run their normal paths without torch."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[2]
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"
# what the gateway may import from the worker package: torch-free helpers it shares with the workers' runtime
GATEWAY_MAY_IMPORT = {"worker.runtime.archive", "worker.runtime.connection", "worker.runtime.failpoints",
                      "worker.runtime.outage", "worker.settings_choice"}


def _lint_imports(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)


def test_import_contracts_hold():
    result = _lint_imports()
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


def test_lint_imports_fails_on_a_broken_contract(tmp_path):
    # the session runtime imports torch (lazily, to preload the engine): a contract forbidding it must break
    config = tmp_path / "contracts.toml"
    config.write_text(textwrap.dedent("""
        [tool.importlinter]
        root_packages = ["worker"]
        include_external_packages = true

        [[tool.importlinter.contracts]]
        name = "a contract the code breaks"
        type = "forbidden"
        source_modules = ["worker.runtime.engine"]
        forbidden_modules = ["torch"]
    """))
    result = _lint_imports("--config", str(config))
    assert result.returncode != 0 and "BROKEN" in result.stdout, result.stdout + result.stderr


def test_the_gateway_imports_only_the_shared_worker_helpers():
    graph = grimp.build_graph("service", "worker", "protocol", include_external_packages=False)
    imported = {target for module in graph.find_descendants("service") | {"service"}
                for target in graph.find_modules_directly_imported_by(module) if target.startswith("worker")}
    assert imported <= GATEWAY_MAY_IMPORT, sorted(imported - GATEWAY_MAY_IMPORT)


def test_gateway_and_sdk_run_without_torch():
    script = textwrap.dedent("""
        import sys

        import msgpack
        import numpy as np

        from client.frames import CameraIntrinsics, StreamFrame
        from client.sdk import FlashMonoClient
        from client.streaming import encode_frame_message
        from protocol.codec import unpack
        from protocol.presets import check_preset
        from service.app import create_app
        from service.frame_validation import check_frame_message
        from service.routes_results import tum_text
        from service.settings import Settings

        assert FlashMonoClient
        app = create_app(Settings(api_keys={"k": frozenset({"admin"})}))
        assert "x-websocket" in app.openapi()
        check_preset("rgbd")
        frame = StreamFrame(index=0, timestamp=0.5, image=np.zeros((48, 64, 3), np.uint8),
                            intrinsics=CameraIntrinsics(50.0, 50.0, 32.0, 24.0), depth=np.ones((48, 64)),
                            pose=np.eye(4))
        from client.streaming import WireOptions
        data = encode_frame_message(frame, 3, WireOptions(send_depth=True, send_pose=True))
        assert check_frame_message(data, 1 << 20, None).seq == 3 and unpack(data)["type"] == "frame"
        assert len(tum_text([{"timestamp": 0.0, "pose": np.eye(4).reshape(-1).tolist()}]).splitlines()) == 2
        print(sorted(m for m in sys.modules if m == "torch" or m.startswith("torch.")))
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]", result.stdout
