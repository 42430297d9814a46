"""Saved maps in the web viewer, in headless Chromium (software WebGL2) against a real stack: a real finished session
of the SLAM engine, its map saved with POST /v1/maps, a session of another room created in that map (tracked, never
relocalized) and one created there without frames. The map list shows the map; opening the map loads its splats,
draws its building session's trajectory and marks the sessions whose poses are not in its world; the map and the
session open on an overview from outside their bounds; a finished session's entry says finished, not tracking.
Screenshots are kept in $FLASHMONO_TEST_ARTIFACTS (default .test-artifacts/)."""

from __future__ import annotations

import asyncio
import os
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

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
ARTIFACTS = Path(os.environ.get("FLASHMONO_TEST_ARTIFACTS", REPO / ".test-artifacts")) / "viewer"
KEY = "maps"
WEBGL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


@pytest.fixture(scope="module")
def world():
    """The stack, a finished real RGB-D session (12 ICL frames), the map saved from it (its JSON), the builder's
    trajectory, and two sessions created in the map: another room streamed (never relocalized) and one idle."""
    with LiveStack(workers=1, api_keys=f"{KEY}=read,stream", engine="slam",
                   extra_env={"FLASHMONO_LOG_LEVEL": "WARNING", "FLASHMONO_REQUEST_TIMEOUT_S": "120"}) as stack:
        frames = list(open_frames(DATA / "icl_mini", max_frames=12, stride=3, use_gt_poses=True))
        wire = WireOptions(send_depth=True, send_pose=True)
        with FlashMonoClient(stack.url, api_key=KEY) as client:
            builder = client.create_session(intrinsics=frames[0].intrinsics, preset="rgbd", name="map-builder",
                                            skip_frames=False)
            client.stream(builder.id, frames, wire=wire, max_pending=4)
            created = httpx.post(f"{stack.url}/v1/maps", json={"session_id": builder.id, "name": "living room"},
                                 headers={"X-API-Key": KEY}, timeout=120)
            assert created.status_code == 201, created.text
            saved = created.json()
            other = list(open_frames(DATA / "tum_fr1_rpy_mini", max_frames=6))
            stranger = client.create_session(intrinsics=other[0].intrinsics, preset="rgbd", name="other-room",
                                             skip_frames=False, map_id=saved["id"])
            client.stream(stranger.id, other, wire=WireOptions(send_depth=True), max_pending=4)
            idle = client.create_session(name="not-started", map_id=saved["id"])
            path = [p.pose for p in client.trajectory(builder.id).poses]
            records = {s: client.get_session(s) for s in (builder.id, stranger.id)}
        assert records[builder.id].status == records[stranger.id].status == "finished"
        assert records[stranger.id].tracking_state == "not_relocalized"
        yield {"stack": stack, "builder": builder.id, "map": saved, "path": np.asarray(path, np.float64),
               "stranger": stranger.id, "idle": idle.id}


async def _open(page: Browser, url: str) -> None:
    await page.navigate(url)
    await page.wait_for("window.viewerState && window.viewerState.splat.ready", 60)


def _camera(pose: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """The position and viewing direction (OpenCV: +z) of a camera-to-world pose."""
    m = np.asarray(pose, np.float64).reshape(4, 4)
    return m[:3, 3], m[:3, 2] / np.linalg.norm(m[:3, 2])


def _assert_overview(pose: list[float], bounds: dict, intrinsics: dict) -> None:
    """The camera is outside the box, looks at its centre, and sees all of it."""
    lo, hi = np.asarray(bounds["min"]), np.asarray(bounds["max"])
    position, forward = _camera(pose)
    assert np.any((position < lo) | (position > hi)), (position, bounds)
    to_centre = (lo + hi) / 2 - position
    angle = np.degrees(np.arccos(np.clip(forward @ to_centre / np.linalg.norm(to_centre), -1, 1)))
    assert angle < 0.5, angle
    m = np.asarray(pose, np.float64).reshape(4, 4)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    local = (corners - m[:3, 3]) @ m[:3, :3]  # world to camera (rotation only: pose() is rigid)
    assert (local[:, 2] > 0).all()
    u = intrinsics["fx"] * local[:, 0] / local[:, 2] + intrinsics["cx"]
    v = intrinsics["fy"] * local[:, 1] / local[:, 2] + intrinsics["cy"]
    assert ((u >= 0) & (u <= intrinsics["width"]) & (v >= 0) & (v <= intrinsics["height"])).all(), (u, v)


def test_the_map_list_shows_the_map_and_a_finished_session_says_finished(chromium, world) -> None:
    stack, saved, meta = world["stack"], world["map"], world["map"]["meta"]

    async def scenario() -> dict:
        async with Browser(chromium) as page:
            await page.navigate(f"{stack.url}/viewer?api_key={KEY}")
            entry = f"#maps li[data-id=\"{saved['id']}\"]"
            await page.wait_for(f"document.querySelector('{entry}') !== null", 30)
            await page.wait_for(f"document.querySelector('#sessions li[data-id=\"{world['builder']}\"]') !== null", 30)
            texts = await page.evaluate("Object.fromEntries([...document.querySelectorAll('.entries li')]"
                                        ".map((li) => [li.dataset.id, li.textContent]))")
            more_hidden = await page.evaluate("[document.getElementById('more-maps').hidden,"
                                              " document.getElementById('more-sessions').hidden]")
            await page.evaluate(f"document.querySelector('{entry} a').click()")
            opened = await page.wait_for("new URLSearchParams(location.search).get('map')", 10)
            return {"texts": texts, "more_hidden": more_hidden, "opened": opened,
                    "errors": list(page.console_errors)}

    result = asyncio.run(scenario())
    assert result["errors"] == [], result["errors"]
    listed = result["texts"][saved["id"]]
    for fact in ("living room", "v1", f"{meta['keyframes']} keyframes", f"{meta['surfels']:,} surfels",
                 f"{saved['size_bytes'] / 1e6:.2f} MB", "metric", "built by 1 session"):
        assert fact in listed, (fact, listed)
    assert result["more_hidden"] == [True, True]  # one page holds everything
    assert result["opened"] == saved["id"]
    # finished sessions say so, and no tracking state (the records keep the worker's last one)
    for sid in (world["builder"], world["stranger"]):
        assert "finished · " in result["texts"][sid] and "tracking" not in result["texts"][sid], result["texts"][sid]
    assert "created · 0 frames" in result["texts"][world["idle"]]
    assert "tracking: waiting" in result["texts"][world["idle"]]  # live, without frames yet


def test_the_list_pages_through_the_api_cursor(chromium, world) -> None:
    """PagedList against a fake API of 7 records in pages of 3: "more" appends the next page until there is none, a
    refresh reloads as many as are shown, and the selection survives redraws."""
    stack = world["stack"]
    script = """(async () => {
      const { PagedList } = await import('/viewer/static/lists.js');
      const ids = [...Array(7).keys()].map((i) => `r${i}`);
      const calls = [];
      const list = document.createElement('ul'), more = document.createElement('button');
      document.body.append(list, more);
      const paged = new PagedList({ list, more, pageSize: 3,
        fetchPage: async (limit, cursor) => {
          calls.push([limit, cursor]);
          const start = cursor ? ids.indexOf(cursor) + 1 : 0;
          const items = ids.slice(start, start + limit).map((id) => ({ id }));
          return { items, next: start + limit < ids.length ? items[items.length - 1].id : null };
        },
        entry: (item) => { const li = document.createElement('li'); li.dataset.id = item.id; return li; } });
      const shown = () => [...list.children].map((li) => li.dataset.id);
      const steps = [];
      await paged.refresh(); steps.push([shown(), more.hidden]);
      paged.select('r1');
      more.click(); await paged.queue; steps.push([shown(), more.hidden]);
      await paged.more(); steps.push([shown(), more.hidden]);
      await paged.refresh(); steps.push([shown(), more.hidden]);
      return { steps, calls, selected: [...list.querySelectorAll('li.selected')].map((li) => li.dataset.id) };
    })()"""

    async def scenario() -> dict:
        async with Browser(chromium) as page:
            await page.navigate(f"{stack.url}/viewer?api_key={KEY}")
            await page.wait_for("window.viewerState !== undefined", 30)
            return await page.evaluate(script)

    result = asyncio.run(scenario())
    ids = [f"r{i}" for i in range(7)]
    assert result["steps"] == [[ids[:3], False], [ids[:6], False], [ids, True], [ids, True]]
    assert result["calls"] == [[3, None], [3, "r2"], [3, "r5"], [7, None]]
    assert result["selected"] == ["r1"]


def test_opening_the_map_shows_its_splats_and_sessions_from_outside_its_bounds(chromium, world) -> None:
    stack, saved = world["stack"], world["map"]
    meta, map_id, builder = saved["meta"], saved["id"], world["builder"]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)

    async def scenario() -> dict:
        async with Browser(chromium, extra_flags=WEBGL_FLAGS) as page:
            await _open(page, f"{stack.url}/viewer?map={map_id}&api_key={KEY}")
            loaded = await page.wait_for("window.viewerState.splat.map", 90)
            await page.wait_for("window.viewerState.map && window.viewerState.map.sessions.length === 3", 30)
            frames = await page.evaluate("window.splatView.frames")
            await page.wait_for(f"window.splatView.frames >= {frames + 5}", 60)
            await asyncio.sleep(1.0)  # Spark sorts in a worker: let the order settle
            shot = await page.screenshot(await page.evaluate(
                "(() => { const r = document.getElementById('splats').getBoundingClientRect();"
                " return {x: r.x, y: r.y, width: r.width, height: r.height}; })()"))
            state = await page.evaluate("({map: window.viewerState.map, overview: window.viewerState.splat.overview,"
                                        " pose: window.splatView.pose(), k: window.splatView.viewIntrinsics(),"
                                        " layers: window.splatView.layers, mode: document.body.dataset.mode,"
                                        " title: document.getElementById('session-title').textContent,"
                                        " hidden: getComputedStyle(document.getElementById('topdown')"
                                        ".closest('figure')).display})")
            (ARTIFACTS / "map_page.png").write_bytes(await page.screenshot())
            legend = await page.evaluate("[...document.querySelectorAll('#map-legend li')].map((li) =>"
                                         " [li.dataset.id, li.dataset.drawn, li.textContent])")
            await page.evaluate("document.getElementById('splat-to-pose').click()")
            at_pose = await page.evaluate("window.splatView.pose()")
            await page.evaluate("document.getElementById('splat-overview').click()")
            back = await page.evaluate("window.splatView.pose()")
            return {"loaded": loaded, "shot": shot, "state": state, "legend": legend, "at_pose": at_pose,
                    "back": back, "errors": list(page.console_errors),
                    "last_error": await page.evaluate("window.viewerState.lastError")}

    result = asyncio.run(scenario())
    (ARTIFACTS / "map_overview.png").write_bytes(result["shot"])
    assert result["errors"] == [] and result["last_error"] is None, (result["errors"], result["last_error"])
    state = result["state"]
    assert state["mode"] == "map" and state["hidden"] == "none" and "living room" in state["title"]
    # the map's splats: its SPZ, every surfel
    assert result["loaded"]["format"] == "spz" and result["loaded"]["splats"] == meta["surfels"]
    assert result["loaded"]["key"].startswith(f"{map_id}|v1|")
    image = cv2.imdecode(np.frombuffer(result["shot"], np.uint8), cv2.IMREAD_COLOR)
    assert image.std() > 5, "the map drew a blank frame"
    # the builder's trajectory drawn in its colour; the others listed, marked, not drawn
    sessions = {s["id"]: s for s in state["map"]["sessions"]}
    assert sessions[builder]["drawn"] and sessions[builder]["poses"] == len(world["path"])
    assert state["layers"] == [{"id": builder, "poses": len(world["path"]), "color": sessions[builder]["color"]}]
    legend = {sid: (drawn, text) for sid, drawn, text in result["legend"]}
    assert legend[builder][0] == "true" and "built" in legend[builder][1]
    assert legend[world["stranger"]][0] == "false" and "never relocalized" in legend[world["stranger"]][1]
    assert legend[world["idle"]][0] == "false" and "no poses yet" in legend[world["idle"]][1]
    # the camera starts outside the map's bounds, looking at its centre, the whole box in view
    assert result["state"]["overview"]["bounds"] == meta["bounds"]
    _assert_overview(state["pose"], meta["bounds"], state["k"])
    # "to latest pose" goes to the builder's last pose; "overview" comes back
    assert np.allclose(_camera(result["at_pose"])[0], world["path"][-1].reshape(4, 4)[:3, 3], atol=1e-4)
    assert np.allclose(result["back"], state["pose"], atol=1e-5)


def test_a_finished_session_opens_on_an_overview_not_at_its_last_pose(chromium, world) -> None:
    stack, builder, path = world["stack"], world["builder"], world["path"]

    async def scenario() -> dict:
        async with Browser(chromium, extra_flags=WEBGL_FLAGS) as page:
            await _open(page, f"{stack.url}/viewer?session={builder}&api_key={KEY}")
            await page.wait_for("window.viewerState.splat.map", 90)
            return await page.evaluate("({overview: window.viewerState.splat.overview, pose: window.splatView.pose(),"
                                       " k: window.splatView.viewIntrinsics(), errors: window.viewerState.lastError})")

    result = asyncio.run(scenario())
    assert result["errors"] is None
    bounds = result["overview"]["bounds"]
    centres = path.reshape(-1, 4, 4)[:, :3, 3]
    assert (centres >= np.asarray(bounds["min"]) - 1e-6).all() and (centres <= np.asarray(bounds["max"]) + 1e-6).all()
    _assert_overview(result["pose"], bounds, result["k"])
    assert np.linalg.norm(_camera(result["pose"])[0] - centres[-1]) > 0.1  # not at the last pose
    # its own box: the path's and its splats' (1st to 99th percentile of the centres, as the saved map's metadata)
    saved = world["map"]["meta"]["bounds"]
    assert (np.asarray(bounds["min"]) <= np.asarray(saved["min"]) + 0.01).all()
    assert (np.asarray(bounds["max"]) >= np.asarray(saved["max"]) - 0.01).all()
