"""The docker/ files: no Docker engine runs here, so check their structure (compose YAML, Dockerfile commands)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import yaml

DOCKER_DIR = Path(__file__).resolve().parents[2] / "docker"


def _compose() -> dict:
    return yaml.safe_load((DOCKER_DIR / "compose.yaml").read_text())


def _dockerfile_cmd(name: str) -> list[str]:
    text = (DOCKER_DIR / name).read_text()
    match = re.search(r"^CMD (\[.*\])\s*$", text, re.MULTILINE)
    assert match, f"{name} has no exec-form CMD"
    return yaml.safe_load(match.group(1))


def test_compose_has_redis_a_gateway_and_two_gpu_workers() -> None:
    compose = _compose()
    services = compose["services"]
    assert set(services) == {"redis", "gateway", "worker-0", "worker-1"}
    assert services["redis"]["image"].startswith("redis:")
    assert services["gateway"]["build"]["dockerfile"] == "docker/Dockerfile.gateway"
    assert "8000:8000" in services["gateway"]["ports"]
    gpus = []
    for name in ("worker-0", "worker-1"):
        worker = services[name]
        assert worker["build"]["dockerfile"] == "docker/Dockerfile.worker"
        assert worker["depends_on"]["redis"]["condition"] == "service_healthy"
        (device,) = worker["deploy"]["resources"]["reservations"]["devices"]
        assert device["driver"] == "nvidia" and "gpu" in device["capabilities"]
        gpus += device["device_ids"]
    assert sorted(gpus) == ["0", "1"], "each worker owns its own GPU"


def test_every_service_talks_to_the_same_redis() -> None:
    services = _compose()["services"]
    urls = {services[name]["environment"]["REDIS_URL"] for name in ("gateway", "worker-0", "worker-1")}
    assert urls == {"redis://redis:6379/0"}
    assert "redis" in services  # the host name in REDIS_URL is the compose service


def test_build_contexts_are_the_repository_root() -> None:
    for name, service in _compose()["services"].items():
        if "build" in service:
            context = (DOCKER_DIR / service["build"]["context"]).resolve()
            assert (context / "pyproject.toml").is_file(), name
            assert (context / service["build"]["dockerfile"]).is_file(), name


def test_worker_image_is_cuda_with_gsplat_and_runs_the_worker_module() -> None:
    text = (DOCKER_DIR / "Dockerfile.worker").read_text()
    assert re.search(r"^FROM nvidia/cuda:\S+devel", text, re.MULTILINE), "worker needs a CUDA devel base for gsplat"
    assert "gsplat" in text
    cmd = _dockerfile_cmd("Dockerfile.worker")
    assert cmd[:2] == ["python", "-m"]
    assert importlib.util.find_spec(cmd[2]) is not None, f"{cmd[2]} does not exist"


def test_gateway_image_runs_the_serve_command_without_local_workers() -> None:
    cmd = _dockerfile_cmd("Dockerfile.gateway")
    assert cmd[:2] == ["flashmono", "serve"]
    assert cmd[cmd.index("--workers") + 1] == "0"
    from client.cli import build_parser

    args = build_parser().parse_args(cmd[1:])  # the flags exist
    assert args.command == "serve"
