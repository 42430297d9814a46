"""`flashmono serve` as a real process: its --help states the defaults, a server without API keys says at start-up
that it is open, and SIGTERM (kill, systemd, docker stop) stops the gateway, its workers and the embedded Redis and
removes Redis's temp dir, like Ctrl-C."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
from live_stack import REPO_ROOT, free_port


def _serve_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "client.cli", "serve", *args]


def test_serve_help_states_the_defaults() -> None:
    text = subprocess.run(_serve_command("--help"), capture_output=True, text=True, cwd=REPO_ROOT, check=True).stdout
    flat = " ".join(text.split())
    for default in ("(default: 127.0.0.1)", "(default: 8000)", "default: 1)", "(default: info)", "default 10"):
        assert default in flat, f"{default!r} missing from serve --help"


def _children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is `pid`."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]
        if int(ppid) == pid and state != "Z":
            found.append(int(entry.name))
    return found


def _descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        for child in _children(todo.pop()):
            out.append(child)
            todo.append(child)
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _cmdline(pid: int) -> list[str]:
    return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")


def test_sigterm_stops_every_child_and_removes_the_temp_dir(tmp_path) -> None:
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "REDIS_URL"}
    env.update(FLASHMONO_TORCH_THREADS="1", OMP_NUM_THREADS="1", FLASHMONO_DATA_DIR=str(tmp_path / "data"))
    log = open(tmp_path / "serve.log", "w")
    serve = subprocess.Popen(_serve_command("--port", str(port), "--workers", "1", "--engine", "passthrough",
                                            "--log-level", "warning"),
                             cwd=REPO_ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    children: list[int] = []
    try:
        deadline = time.monotonic() + 180
        while True:
            assert serve.poll() is None, (tmp_path / "serve.log").read_text()
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).json().get("workers", 0) >= 1:
                    break
            except (httpx.TransportError, ValueError):
                pass
            assert time.monotonic() < deadline, "serve was not ready in time"
            time.sleep(0.3)
        children = _descendants(serve.pid)
        redis = [pid for pid in children if "redis-server" in _cmdline(pid)[0]]
        workers = [pid for pid in children if "worker.runtime.main" in _cmdline(pid)]
        assert len(redis) == 1 and len(workers) == 1, [_cmdline(pid) for pid in children]
        title = " ".join(_cmdline(redis[0]))  # redis-server retitles itself "... unixsocket:/path/redis.sock"
        socket_dir = Path(re.search(r"unixsocket[: ]+(\S+)", title).group(1)).parent
        assert socket_dir.is_dir()

        assert "AUTH IS OFF" in (tmp_path / "serve.log").read_text()  # no keys: open, and the log says so

        serve.send_signal(signal.SIGTERM)
        assert serve.wait(timeout=60) == 0, (tmp_path / "serve.log").read_text()
        survivors = [pid for pid in children if _alive(pid)]
        assert survivors == [], [_cmdline(pid) for pid in survivors]
        assert not socket_dir.exists(), "the embedded Redis's temp dir was left behind"
    finally:  # leave nothing behind when an assertion failed
        if serve.poll() is None:
            serve.kill()
            serve.wait()
        for pid in children:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        log.close()
