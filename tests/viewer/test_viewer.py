"""The web viewer in headless Chromium against a real stack with a live session: the page lists sessions, draws
the trajectory (pixels in the canvases), renders a view from a camera the user moves, downloads the map, and
logs no console errors."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from live_stack import LiveStack

from client.sdk import FlashMonoClient
from client.streaming import WireOptions, open_frames

sys.path.insert(0, str(Path(__file__).parent))
from cdp import Browser  # noqa: E402

ENGINE = "passthrough"  # the page is under test, not the engine; the SLAM compute would only add minutes
PRESET = "test"
BACKGROUND = np.array([17, 14, 11])  # the canvas background #0b0e11, in BGR


@pytest.fixture(scope="module")
def live_session():
    with LiveStack(workers=1, api_keys="viewer=read,stream", engine=ENGINE) as stack:
        data = Path(__file__).resolve().parents[1] / "data" / "icl_mini"
        frames = list(open_frames(data, max_frames=16, stride=2, resize=(160, 120), use_gt_poses=True))
        with FlashMonoClient(stack.url, api_key="viewer") as client:
            session = client.create_session(intrinsics=frames[0].intrinsics, preset=PRESET, name="viewer-walk",
                                            skip_frames=False)  # recorded frames: every one tracked
            client.stream(session.id, frames, wire=WireOptions(send_depth=True, send_pose=True), max_pending=4)
        yield stack, session.id, len(frames)


def _foreground_pixels(png: bytes) -> int:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return int((np.abs(image.astype(int) - BACKGROUND).sum(axis=2) > 60).sum())


async def _clip(page: Browser, element_id: str) -> dict:
    return await page.evaluate(
        f"(() => {{ const r = document.getElementById('{element_id}').getBoundingClientRect();"
        " return {x: r.x, y: r.y, width: r.width, height: r.height}; })()")


async def _downloaded_file(directory: Path, name: str, timeout_s: float) -> bytes:
    """The bytes of `name` once Chromium has finished writing it (it renames a .crdownload file when done)."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    target = directory / name
    while not target.is_file():
        if asyncio.get_running_loop().time() > deadline:
            raise TimeoutError(f"{name} did not appear in {directory}: {sorted(p.name for p in directory.iterdir())}")
        await asyncio.sleep(0.1)
    return target.read_bytes()


def test_viewer_draws_a_live_session_renders_and_downloads(chromium, live_session, tmp_path: Path) -> None:
    stack, session_id, frame_count = live_session
    downloads = tmp_path / "downloads"
    downloads.mkdir()

    async def scenario() -> dict:
        async with Browser(chromium) as page:
            await page.allow_downloads(downloads)
            await page.navigate(f"{stack.url}/viewer?session={session_id}&api_key=viewer")
            await page.wait_for(f"window.viewerState && window.viewerState.posesDrawn >= {frame_count}", 60)
            await page.wait_for("window.viewerState.renders >= 1", 60)
            listed = await page.wait_for(
                f"document.querySelector('#sessions li[data-id=\"{session_id}\"]') !== null", 20)
            # the key left the address bar (history, bookmarks, Referer) for this tab's sessionStorage only
            address = await page.evaluate("window.location.href")
            stored = await page.evaluate("[sessionStorage.getItem('flashmono.apiKey'), "
                                         "localStorage.getItem('flashmono.apiKey')]")
            shots = {name: await page.screenshot(await _clip(page, name)) for name in ("topdown", "view3d", "render")}
            blank = await page.screenshot({"x": 0, "y": 0, "width": 40, "height": 40})
            # Move the camera: a new render is requested and shown.
            await page.evaluate("document.querySelector('[data-move=forward]').click()")
            await page.wait_for("window.viewerState.renders >= 2", 30)
            await page.evaluate("document.getElementById('download-map').click()")
            status = await page.wait_for(
                "document.getElementById('map-status').textContent.startsWith('map downloaded') && "
                "document.getElementById('map-status').textContent", 30)
            last_map = await page.evaluate("window.viewerState.lastMap")
            saved = await _downloaded_file(downloads, f"{session_id}.ply", 30)
            await asyncio.sleep(1.5)  # past the next trajectory poll: the outcome must stay on screen
            status_later = await page.evaluate("document.getElementById('map-status').textContent")
            stats = await page.evaluate("document.getElementById('session-stats').textContent")
            splat_info = await page.wait_for("window.viewerState.splat.mapError", 20)
            return {"shots": shots, "blank": blank, "status": status, "status_later": status_later,
                    "last_map": last_map, "saved": saved, "stats": stats, "listed": listed, "splat_info": splat_info,
                    "errors": list(page.console_errors), "address": address, "stored": stored,
                    "last_error": await page.evaluate("window.viewerState.lastError")}

    result = asyncio.run(scenario())
    # The passthrough engine keeps camera centres, not Gaussians: the splat view's map request is refused (409) and
    # the page says so beside the view; nothing else may fail (the viewer's CSP blocks nothing it needs).
    expected = f"409 (Conflict) {stack.url}/v1/sessions/{session_id}/map?format=spz"
    assert [e for e in result["errors"] if not e.endswith(expected)] == [], result["errors"]
    assert "cannot be written as spz" in result["splat_info"]
    assert result["address"] == f"{stack.url}/viewer?session={session_id}"
    assert result["stored"] == ["viewer", None]
    assert result["last_error"] is None
    assert result["listed"]
    assert f"{frame_count}/{frame_count} frames" in result["stats"]
    # The map the browser saved is the map the server serves, and the page says so (and keeps saying so).
    with FlashMonoClient(stack.url, api_key="viewer") as client:
        served = client.download_map(session_id)
    assert result["saved"] == served
    assert served.startswith(b"ply\n") and f"element vertex {frame_count}".encode() in served
    assert result["last_map"] == {"name": f"{session_id}.ply", "bytes": len(served)}
    assert result["status"] == f"map downloaded: {session_id}.ply ({len(served)} bytes)"
    assert result["status_later"] == result["status"]
    topdown = _foreground_pixels(result["shots"]["topdown"])
    view3d = _foreground_pixels(result["shots"]["view3d"])
    assert topdown > 150, f"the top-down trajectory drew only {topdown} pixels"
    assert view3d > 150, f"the 3D trajectory drew only {view3d} pixels"
    render = cv2.imdecode(np.frombuffer(result["shots"]["render"], np.uint8), cv2.IMREAD_COLOR)
    assert render.std() > 1.0, "the rendered view is blank"
    assert _foreground_pixels(result["blank"]) < 40 * 40  # sanity: the page background is not counted


def test_viewer_without_a_key_reports_the_auth_error_in_the_page(chromium, live_session) -> None:
    stack, session_id, _ = live_session

    async def scenario() -> tuple[str, list[str]]:
        async with Browser(chromium) as page:
            await page.navigate(f"{stack.url}/viewer?session={session_id}&api_key=wrong")
            text = await page.wait_for("window.viewerState && window.viewerState.lastError", 30)
            return text, list(page.console_errors)

    text, errors = asyncio.run(scenario())
    assert "key" in text.lower() or "401" in text
    # The browser itself logs the failed (401) requests; nothing else may fail.
    assert all("401" in e for e in errors), errors


def test_events_feed_refuses_bad_keys_and_reports_a_finished_session(live_session) -> None:
    import json

    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    stack, session_id, frame_count = live_session
    ws_url = stack.url.replace("http", "ws", 1) + f"/v1/sessions/{session_id}/events"
    with connect(f"{ws_url}?api_key=wrong", open_timeout=10) as ws:
        refusal = json.loads(ws.recv(timeout=10))
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)
    assert refusal["type"] == "error" and refusal["code"] == "unauthorized"
    assert ws.close_code == 4401
    with connect(f"{ws_url}?api_key=viewer", open_timeout=10) as ws:
        first = json.loads(ws.recv(timeout=10))
    assert first == {"type": "finished", "frames": frame_count}


def test_fleet_list_shows_state_filters_and_links_to_views(chromium, live_session) -> None:
    stack, finished_id, frame_count = live_session
    with FlashMonoClient(stack.url, api_key="viewer") as client:
        waiting = client.create_session(name="fleet-waiting", device_id="phone-9")
    raw = httpx.get(f"{stack.url}/v1/sessions", headers={"X-API-Key": "viewer"}).json()["sessions"]
    by_id = {s["id"]: s for s in raw}
    assert by_id[waiting.id]["tracking_state"] is None and by_id[waiting.id]["frames_processed"] == 0
    keyframes = by_id[finished_id]["keyframes"]
    assert keyframes >= 1

    async def scenario() -> dict:
        async with Browser(chromium) as page:
            await page.navigate(f"{stack.url}/viewer?api_key=viewer")
            await page.wait_for(f"document.querySelector('#sessions li[data-id=\"{waiting.id}\"]') !== null", 30)
            texts = await page.evaluate("Object.fromEntries([...document.querySelectorAll('#sessions li')]"
                                        ".map((li) => [li.dataset.id, li.textContent]))")
            link = await page.evaluate(f"document.querySelector('#sessions li[data-id=\"{finished_id}\"] a')"
                                       ".getAttribute('href')")
            await page.evaluate("(() => { const f = document.getElementById('session-filter'); f.value = 'phone-9';"
                                " f.dispatchEvent(new Event('input')); })()")
            by_text = await page.evaluate("[...document.querySelectorAll('#sessions li')].map((li) => li.dataset.id)")
            await page.evaluate("(() => { document.getElementById('session-filter').value = '';"
                                " const s = document.getElementById('status-filter'); s.value = 'finished';"
                                " s.dispatchEvent(new Event('change')); })()")
            by_status = await page.evaluate("[...document.querySelectorAll('#sessions li')]"
                                            ".map((li) => li.dataset.status)")
            await page.evaluate(f"document.querySelector('#sessions li[data-id=\"{finished_id}\"] a').click()")
            selected = await page.wait_for("new URLSearchParams(location.search).get('session')", 10)
            return {"texts": texts, "link": link, "by_text": by_text, "by_status": by_status, "selected": selected,
                    "errors": list(page.console_errors)}

    result = asyncio.run(scenario())
    assert result["errors"] == [], result["errors"]
    assert f"finished · {frame_count} frames · {keyframes} keyframes · last pose" in result["texts"][finished_id]
    assert "tracking: waiting" in result["texts"][waiting.id] and "created · 0 frames" in result["texts"][waiting.id]
    # the record keeps the worker's last tracking state; the list shows one only while the session is live
    assert by_id[finished_id]["tracking_state"] == "tracking" and "tracking" not in result["texts"][finished_id]
    assert result["link"] == f"/viewer?session={finished_id}" and result["selected"] == finished_id
    assert result["by_text"] == [waiting.id]
    assert result["by_status"] and set(result["by_status"]) == {"finished"}
