"""Workers that die are restarted (with back-off while they keep dying), and `flashmono serve` keeps its sessions
across a restart (the embedded Redis's append-only file in --data-dir)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
from runtime_helpers import wait_for

from service.launcher import free_port
from service.supervisor import WorkerSupervisor

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_supervisor_restarts_dead_processes_and_backs_off():
    supervisor = WorkerSupervisor(lambda: subprocess.Popen(["sleep", "60"]), count=2, poll_s=0.02,
                                  first_delay_s=0.05, max_delay_s=0.4)
    supervisor.start()
    try:
        first = supervisor.workers[0]
        first.kill()
        wait_for(lambda: supervisor.workers[0].pid != first.pid, timeout_s=10)
        assert supervisor.restarts == 1 and supervisor.workers[0].poll() is None
        assert supervisor.workers[1].poll() is None  # the other one was left alone
        # a process that dies at once is restarted ever more slowly: the delays double up to max_delay_s
        supervisor.spawn = lambda: subprocess.Popen(["false"])
        supervisor.workers[1].kill()
        time.sleep(1.5)
        assert 3 <= supervisor.restarts <= 8
    finally:
        supervisor.stop()
    assert all(p.poll() is not None for p in supervisor.workers)


def _children(pid: int, marker: str) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if int(fields[1]) == pid and marker in cmdline:
            found.append(int(stat.parent.name))
    return found


def _serve(port: int, data_dir: Path) -> subprocess.Popen:
    env = {**os.environ, "FLASHMONO_LEASE_TTL_MS": "3000", "OMP_NUM_THREADS": "1"}
    env.pop("REDIS_URL", None)
    return subprocess.Popen([sys.executable, "-m", "client.cli", "serve", "--port", str(port), "--engine",
                             "passthrough", "--data-dir", str(data_dir), "--log-level", "warning"], cwd=REPO_ROOT,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=2).status_code == 200
    except httpx.TransportError:
        return False


def test_serve_restarts_a_killed_worker_and_keeps_sessions_across_restarts(tmp_path):
    data_dir = tmp_path / "data"
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    serve = _serve(port, data_dir)
    try:
        wait_for(lambda: _ready(url), timeout_s=120, interval_s=0.2)
        sid = httpx.post(f"{url}/v1/sessions", json={"name": "kept"}).json()["id"]
        [worker] = _children(serve.pid, "worker.runtime.main")
        os.kill(worker, signal.SIGKILL)
        replacement = wait_for(lambda: [p for p in _children(serve.pid, "worker.runtime.main") if p != worker],
                               timeout_s=30)
        assert len(replacement) == 1
        wait_for(lambda: _ready(url), timeout_s=60, interval_s=0.2)
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(timeout=60)
    assert (data_dir / "flashmono.aof").stat().st_size > 0
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    serve = _serve(port, data_dir)
    try:
        wait_for(lambda: _ready(url), timeout_s=120, interval_s=0.2)
        session = httpx.get(f"{url}/v1/sessions/{sid}").json()
        assert session["name"] == "kept" and session["id"] == sid
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(timeout=60)
