"""A real Flash-Mono stack for client, viewer and end-to-end tests: private Redis, the gateway under uvicorn and
worker processes, each a real process on loopback. Used as a context manager; everything is stopped on exit."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO_ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def receive_until(ws, predicate, timeout_s: float = 60.0) -> list[dict]:
    """A sync WebSocket's JSON messages until one satisfies `predicate` (included); TimeoutError otherwise."""
    messages: list[dict] = []
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError(f"no matching message; got {[m.get('type') for m in messages][-10:]}")
        message = json.loads(ws.recv(timeout=remaining))
        messages.append(message)
        if predicate(message):
            return messages


class LiveStack:
    """Redis + gateway + `workers` worker processes. `url` is the gateway's base URL."""

    def __init__(self, workers: int = 1, api_keys: str = "", engine: str = "slam",
                 extra_env: dict[str, str] | None = None) -> None:
        self.workers = workers
        self.api_keys = api_keys
        self.engine = engine
        self.extra_env = extra_env or {}
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.processes: list[subprocess.Popen] = []
        self.logs = tempfile.mkdtemp(prefix="flashmono-stack-")
        self.redis = None

    def __enter__(self) -> LiveStack:
        from service.redis_embedded import EmbeddedRedis

        self.redis = EmbeddedRedis().start()
        env = {**os.environ, "REDIS_URL": self.redis.url, "FLASHMONO_API_KEYS": self.api_keys,
               "FLASHMONO_TORCH_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", **self.extra_env}
        env.pop("FLASHMONO_API_KEYS_FILE", None)
        try:
            self._spawn("gateway", [sys.executable, "-m", "uvicorn", "service.app:create_app", "--factory",
                                    "--host", "127.0.0.1", "--port", str(self.port), "--log-level", "warning"], env)
            for i in range(self.workers):
                self._spawn(f"worker{i}", [sys.executable, "-m", "worker.runtime.main", "--engine", self.engine,
                                           "--worker-id", f"test-worker-{i}", "--torch-threads", "1"], env)
            self.wait_ready()
        except BaseException:
            self.__exit__()
            raise
        return self

    def _spawn(self, name: str, argv: list[str], env: dict[str, str]) -> None:
        log = open(Path(self.logs) / f"{name}.log", "w")
        self.processes.append(subprocess.Popen(argv, env=env, cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT))

    def wait_ready(self, timeout_s: float = 240.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            for process in self.processes:
                if process.poll() is not None:
                    raise RuntimeError(f"a stack process exited early ({process.args[2]}): {self.log_tail()}")
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the stack was not ready within {timeout_s} s: {self.log_tail()}")
            time.sleep(0.3)

    def log_tail(self, chars: int = 3000) -> str:
        parts = []
        for path in sorted(Path(self.logs).glob("*.log")):
            parts.append(f"--- {path.name}\n{path.read_text(errors='replace')[-chars:]}")
        return "\n".join(parts)

    def __exit__(self, *exc: object) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.terminate()
        for process in self.processes:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        if self.redis is not None:
            self.redis.stop()
