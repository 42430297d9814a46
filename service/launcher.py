"""Start the pieces of a local deployment as processes: Redis (embedded unless a URL is given), the gateway
(uvicorn) and N workers. Used by `flashmono serve`, the tests and the benchmark.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import httpx

from protocol.limits import websocket_max_size
from service.redis_embedded import EmbeddedRedis
from service.settings import Settings


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_worker_process(redis_url: str, env: dict[str, str] | None = None, worker_id: str | None = None,
                         stdout=None, nice: int = 0) -> subprocess.Popen:
    """`python -m worker.runtime.main` against `redis_url` (extra environment in `env`).

    `nice` > 0 runs the worker below the gateway's CPU priority: where both share a machine, the latency-critical
    ingest path (validate, enqueue, ack) then gets a core first and the worker's throughput work the rest."""
    if not 0 <= nice <= 19:
        raise ValueError(f"nice must be within 0..19, got {nice}")
    process_env = {**os.environ, **(env or {}), "REDIS_URL": redis_url}
    if worker_id:
        process_env["FLASHMONO_WORKER_ID"] = worker_id
    process = subprocess.Popen([sys.executable, "-m", "worker.runtime.main"], env=process_env, stdout=stdout,
                               stderr=subprocess.STDOUT if stdout else None)
    if nice:
        os.setpriority(os.PRIO_PROCESS, process.pid, nice)
    return process


def start_gateway_process(redis_url: str, host: str, port: int, env: dict[str, str] | None = None,
                          stdout=None) -> subprocess.Popen:
    """uvicorn serving `service.app:app` on host:port."""
    process_env = {**os.environ, **(env or {}), "REDIS_URL": redis_url}
    max_frame = Settings.from_env(process_env).max_frame_bytes
    args = [sys.executable, "-m", "uvicorn", "service.app:app", "--host", host, "--port", str(port),
            "--log-level", "warning", "--no-access-log", "--ws-max-size", str(websocket_max_size(max_frame))]
    return subprocess.Popen(args, env=process_env, stdout=stdout, stderr=subprocess.STDOUT if stdout else None)


class LocalStack:
    """Redis + gateway + workers as child processes; `stop()` ends them all (also on context exit)."""

    def __init__(self, workers: int = 1, redis_url: str | None = None, host: str = "127.0.0.1",
                 port: int | None = None, gateway_env: dict[str, str] | None = None,
                 worker_env: dict[str, str] | None = None, worker_nice: int = 0) -> None:
        self.host = host
        self.port = port or free_port()
        self.gateway_env = gateway_env or {}
        self.worker_env = worker_env or {}
        self.initial_workers = workers
        self.worker_nice = worker_nice
        self.redis: EmbeddedRedis | None = None
        self.redis_url = redis_url or ""
        self.gateway: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []

    @property
    def base_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def start(self, timeout_s: float = 300.0) -> LocalStack:
        """Start everything and wait until it is ready; on failure, stop what was started and re-raise."""
        try:
            if not self.redis_url:
                self.redis = EmbeddedRedis().start()
                self.redis_url = self.redis.url
            self.gateway = start_gateway_process(self.redis_url, self.host, self.port, self.gateway_env)
            for _ in range(self.initial_workers):
                self.add_worker()
            self.wait_ready(timeout_s, need_workers=self.initial_workers)
        except BaseException:
            self.stop()
            raise
        return self

    def add_worker(self, env: dict[str, str] | None = None, worker_id: str | None = None) -> subprocess.Popen:
        process = start_worker_process(self.redis_url, {**self.worker_env, **(env or {})}, worker_id,
                                       nice=self.worker_nice)
        self.workers.append(process)
        return process

    def wait_ready(self, timeout_s: float, need_workers: int = 1) -> None:
        """Until the gateway answers and at least `need_workers` workers have a heartbeat."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.gateway is not None and self.gateway.poll() is not None:
                raise RuntimeError(f"the gateway exited with code {self.gateway.returncode}")
            try:
                r = httpx.get(f"{self.base_url}/readyz", timeout=2)
                if r.status_code in (200, 503) and r.json().get("workers", 0) >= need_workers:
                    return
                if need_workers == 0 and r.status_code in (200, 503):
                    return
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("the local stack did not become ready in time")
            time.sleep(0.1)

    def stop(self) -> None:
        for process in [*self.workers, self.gateway]:
            if process is not None and process.poll() is None:
                process.terminate()
        for process in [*self.workers, self.gateway]:
            if process is None:
                continue
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        self.workers.clear()
        self.gateway = None
        if self.redis is not None:
            self.redis.stop()
            self.redis = None

    def __enter__(self) -> LocalStack:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
