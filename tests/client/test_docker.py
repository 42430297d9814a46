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
    services = {name: s for name, s in compose["services"].items() if "profiles" not in s}
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
    assert urls == {"${REDIS_URL:-redis://redis:6379/0}"}  # the single instance unless REDIS_URL names another
    assert "redis" in services  # the host name in REDIS_URL is the compose service


def test_cluster_profile_forms_three_primaries_with_a_replica_each() -> None:
    services = _compose()["services"]
    nodes = sorted(name for name, s in services.items() if s.get("profiles") == ["cluster"] and "node" in name)
    assert nodes == [f"redis-node-{i}" for i in range(1, 7)]
    for name in nodes:
        command = services[name]["command"]
        assert command[command.index("--cluster-enabled") + 1] == "yes"
        assert command[command.index("--cluster-announce-hostname") + 1] == name  # each announces itself
    init = services["redis-cluster-init"]
    assert init["profiles"] == ["cluster"] and set(init["depends_on"]) == set(nodes)
    create = " ".join(init["command"][-1].split())
    assert "--cluster-replicas 1" in create and all(f"{n}:6379" in create for n in nodes)
    # the README's command for the profile names seeds that exist, in the URL form the service reads
    from worker.runtime.connection import cluster_seeds

    url = re.search(r"REDIS_URL=(redis\+cluster://\S+)", (DOCKER_DIR / "compose.yaml").read_text()).group(1)
    assert {f"{host}" for host, _ in cluster_seeds(url)[1]} <= set(nodes)


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


def _copied_sources(name: str) -> list[str]:
    """The repository paths a Dockerfile COPYs into the image (sources of every `COPY src... dest`)."""
    text = (DOCKER_DIR / name).read_text()
    return [src for line in re.findall(r"^COPY (.+)$", text, re.MULTILINE) for src in line.split()[:-1]]


def _dockerignored(path: str) -> bool:
    patterns = [line.strip() for line in (DOCKER_DIR.parent / ".dockerignore").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    return any(Path(path).match(p) or path == p or path.startswith(f"{p}/") for p in patterns)


def test_images_copy_every_package_the_distribution_installs() -> None:
    import tomllib

    pyproject = tomllib.loads((DOCKER_DIR.parent / "pyproject.toml").read_text())
    packages = {p.rstrip("*") for p in pyproject["tool"]["setuptools"]["packages"]["find"]["include"]}
    for name in ("Dockerfile.gateway", "Dockerfile.worker"):
        sources = _copied_sources(name)
        assert packages | {"pyproject.toml", "README.md"} <= set(sources), (name, sources)
        for source in sources:
            assert (DOCKER_DIR.parent / source).exists(), f"{name} copies {source}, which does not exist"
            assert not _dockerignored(source), f"{name} copies {source}, which .dockerignore leaves out"


def test_build_context_leaves_out_the_local_environment() -> None:
    for heavy in (".venv", ".git", "demo_out"):
        assert _dockerignored(heavy), f"{heavy} would be sent to the Docker daemon with every build"


def test_builds_without_isolation_install_their_build_tools_first() -> None:
    for name in ("Dockerfile.gateway", "Dockerfile.worker"):
        text = (DOCKER_DIR / name).read_text()
        for match in re.finditer(r"pip install [^\n]*--no-build-isolation", text):
            before = text[:match.start()] + match.group(0)
            assert re.search(r"pip install [^\n]*\bsetuptools\b", before), f"{name}: no setuptools before the build"
