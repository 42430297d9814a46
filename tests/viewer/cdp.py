"""A minimal Chrome DevTools Protocol driver for headless Chromium (over `websockets`), for the viewer tests.

Starts `chromium --headless --remote-debugging-port=0`, opens one page, records console errors, uncaught
exceptions and failed loads, evaluates JavaScript, captures screenshots and lets downloads land in a folder.
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import websockets

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--window-size=1500,1100", "--remote-debugging-port=0",
]


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


def ensure_chromium() -> str:
    """The chromium binary, installed from Debian's `chromium` package when missing (apt-get, as root or through
    passwordless sudo; the package lists are refreshed when the first attempt fails). Raises RuntimeError with the
    reason if impossible."""
    path = find_chromium()
    if path:
        return path
    if shutil.which("apt-get") is None:
        raise RuntimeError("chromium is not installed and apt-get is unavailable")
    prefix = [] if os.geteuid() == 0 else ["sudo", "-n"]
    if prefix and shutil.which("sudo") is None:
        raise RuntimeError("chromium is not installed, and installing it needs root or sudo")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = [*prefix, "apt-get", "install", "-y", "-q", "--no-install-recommends", "chromium"]
    result = subprocess.run(install, capture_output=True, text=True, timeout=900, env=env)
    if result.returncode != 0:  # typically a fresh image without package lists
        subprocess.run([*prefix, "apt-get", "update", "-q"], capture_output=True, text=True, timeout=600, env=env)
        result = subprocess.run(install, capture_output=True, text=True, timeout=900, env=env)
    path = find_chromium()
    if not path:
        raise RuntimeError(f"apt-get install chromium failed: {(result.stderr or result.stdout)[-500:]}")
    return path


class Browser:
    """`async with Browser(binary) as page:` - one headless page driven through CDP."""

    def __init__(self, binary: str, extra_flags: list[str] | None = None) -> None:
        """`extra_flags` are added to CHROMIUM_FLAGS; with any, --disable-gpu is dropped (e.g. to ask for
        software WebGL through --use-angle=swiftshader, or a fake camera)."""
        self.binary = binary
        self.flags = [f for f in CHROMIUM_FLAGS if not (extra_flags and f == "--disable-gpu")] + list(extra_flags or [])
        self.profile = tempfile.mkdtemp(prefix="flashmono-chromium-")
        self.process: subprocess.Popen | None = None
        self.ws: Any = None
        self.session_id: str | None = None
        self.ids = itertools.count(1)
        self.replies: dict[int, asyncio.Future] = {}
        self.console_errors: list[str] = []
        self.reader: asyncio.Task | None = None
        self.reply_timeout_s = 60.0  # a page busy drawing (software WebGL, big maps) answers late
        self.handlers: dict[str, Any] = {}  # CDP event name -> async callback(params), e.g. Fetch.requestPaused

    async def __aenter__(self) -> Browser:
        self.process = subprocess.Popen([self.binary, *self.flags, f"--user-data-dir={self.profile}",
                                         "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not port_file.is_file() or len(port_file.read_text().splitlines()) < 2:
            if time.monotonic() > deadline or self.process.poll() is not None:
                raise RuntimeError("chromium did not start its DevTools endpoint")
            await asyncio.sleep(0.1)
        port, path = port_file.read_text().splitlines()[:2]
        self.ws = await websockets.connect(f"ws://127.0.0.1:{port}{path}", max_size=2**28)
        self.reader = asyncio.create_task(self._read())
        target = await self.send("Target.createTarget", {"url": "about:blank"}, browser=True)
        attached = await self.send("Target.attachToTarget", {"targetId": target["targetId"], "flatten": True},
                                   browser=True)
        self.session_id = attached["sessionId"]
        for domain in ("Runtime.enable", "Log.enable", "Page.enable"):
            await self.send(domain)
        return self

    async def __aexit__(self, *exc: Any) -> None:
        if self.reader:
            self.reader.cancel()
        if self.ws:
            await self.ws.close()
        if self.process:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    async def send(self, method: str, params: dict | None = None, browser: bool = False) -> dict:
        message_id = next(self.ids)
        message: dict[str, Any] = {"id": message_id, "method": method, "params": params or {}}
        if not browser:
            message["sessionId"] = self.session_id
        future = asyncio.get_running_loop().create_future()
        self.replies[message_id] = future
        await self.ws.send(json.dumps(message))
        reply = await asyncio.wait_for(future, timeout=self.reply_timeout_s)
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    async def _read(self) -> None:
        async for raw in self.ws:
            message = json.loads(raw)
            if "id" in message and message["id"] in self.replies:
                self.replies.pop(message["id"]).set_result(message)
                continue
            method, params = message.get("method"), message.get("params", {})
            if method in self.handlers:
                asyncio.get_running_loop().create_task(self.handlers[method](params))
                continue
            if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
                text = " ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", []))
                self.console_errors.append(f"console.{params['type']}: {text}")
            elif method == "Runtime.exceptionThrown":
                details = params.get("exceptionDetails", {})
                description = details.get("exception", {}).get("description") or details.get("text")
                self.console_errors.append(f"exception: {description}")
            elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
                entry = params["entry"]
                self.console_errors.append(f"log: {entry.get('text')} {entry.get('url', '')}")

    async def redirect(self, url_pattern: str, target_for: Any) -> None:
        """Send the page's requests matching `url_pattern` to `target_for(url)` instead (transparently for the page;
        None lets one through): for benchmarks that serve data no session holds at network speed."""

        async def paused(params: dict) -> None:
            target = target_for(params["request"]["url"])
            args = {"requestId": params["requestId"], **({"url": target} if target else {})}
            await self.send("Fetch.continueRequest", args)

        self.handlers["Fetch.requestPaused"] = paused
        await self.send("Fetch.enable", {"patterns": [{"urlPattern": url_pattern}]})

    async def navigate(self, url: str) -> None:
        await self.send("Page.navigate", {"url": url})

    async def allow_downloads(self, directory: Path) -> None:
        """Save the page's downloads under `directory` with their suggested names (headless denies them otherwise)."""
        await self.send("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(directory),
                                                        "eventsEnabled": True}, browser=True)

    async def evaluate(self, expression: str) -> Any:
        result = await self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                      "awaitPromise": True})
        if "exceptionDetails" in result:
            raise RuntimeError(f"evaluating {expression!r} failed: {result['exceptionDetails']}")
        return result.get("result", {}).get("value")

    async def wait_for(self, expression: str, timeout_s: float = 30.0) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                value = await self.evaluate(expression)
            except RuntimeError as err:  # e.g. the page's module has not defined its globals yet
                value, last_error = None, err
            else:
                last_error = None
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"{expression!r} stayed falsy for {timeout_s} s (last error: {last_error})")
            await asyncio.sleep(0.25)

    async def screenshot(self, clip: dict[str, float] | None = None) -> bytes:
        params: dict[str, Any] = {"format": "png"}
        if clip:
            params["clip"] = {**clip, "scale": 1}
        return base64.b64decode((await self.send("Page.captureScreenshot", params))["data"])
