"""The map as Gaussian splats in a real browser: headless Chromium (software WebGL2) loads the viewer from a real
stack whose real SLAM engine mapped a real sequence; the page renders the map with the vendored Spark renderer;
the browser's frame at a tracked pose is compared with the server's render at the same pose and camera; Spark's
own loader reads the SPZ, .splat and PLY files the API serves (the round trip against a reader we did not write);
the page reports its frame rate. Screenshots are kept in $FLASHMONO_TEST_ARTIFACTS (default .test-artifacts/)."""

from __future__ import annotations

import asyncio
import json
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
from worker.mapping.splat_arrays import splat_arrays_from_ply

sys.path.insert(0, str(Path(__file__).parent))
from cdp import Browser  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("FLASHMONO_TEST_ARTIFACTS", REPO / ".test-artifacts")) / "viewer"
KEY = "splats"
WIDTH, HEIGHT = 320, 240
# software WebGL2 (SwiftShader): what a headless machine without a GPU has
WEBGL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def icl_frames(count: int = 12) -> list:
    return list(open_frames(REPO / "tests" / "data" / "icl_mini", max_frames=count, stride=3, use_gt_poses=True))


@pytest.fixture(scope="module")
def stack():
    with LiveStack(workers=1, api_keys=f"{KEY}=read,stream", engine="slam",
                   extra_env={"FLASHMONO_LOG_LEVEL": "WARNING", "FLASHMONO_REQUEST_TIMEOUT_S": "120"}) as live:
        yield live


@pytest.fixture(scope="module")
def mapped_session(stack):
    """A finished session of the real engine on 12 ICL frames (posed RGB-D: the quickest real map)."""
    frames = icl_frames()
    with FlashMonoClient(stack.url, api_key=KEY) as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset="rgbd", name="splat-walk",
                                        skip_frames=False)
        client.stream(session.id, frames, wire=WireOptions(send_depth=True, send_pose=True), max_pending=4)
        session = client.get_session(session.id)
        ply = client.download_map(session.id)
    return stack, session, ply


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    b = b * np.where((a * b).sum(axis=1) < 0, -1.0, 1.0)[:, None]
    return np.degrees(4 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2, 0.0, 1.0)))


def _normal(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1)


async def _canvas_shot(page: Browser) -> bytes:
    clip = await page.evaluate("(() => { const r = document.getElementById('splats').getBoundingClientRect();"
                               " return {x: r.x, y: r.y, width: r.width, height: r.height}; })()")
    return await page.screenshot(clip)


def test_splats_render_in_the_page_like_the_server_and_spark_reads_every_format(chromium, mapped_session):
    stack, session, ply = mapped_session
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    k = session.estimated_intrinsics or session.intrinsics
    with FlashMonoClient(stack.url, api_key=KEY) as client:
        keyframe_pose = client.trajectory(session.id, which="keyframes").poses[-1].pose
    pose = [float(v) for v in np.asarray(keyframe_pose).reshape(-1)]
    reference = splat_arrays_from_ply(ply)
    n = len(reference)
    assert n > 1000, f"the engine mapped only {n} surfels"

    async def scenario() -> dict:
        async with Browser(chromium, extra_flags=WEBGL_FLAGS) as page:
            await page.navigate(f"{stack.url}/viewer?session={session.id}&api_key={KEY}")
            await page.wait_for("window.viewerState && window.viewerState.splat.ready", 60)
            loaded = await page.wait_for("window.viewerState.splat.map", 90)
            # the browser's camera exactly at the keyframe, with the session's pinhole, at the image's size
            await page.evaluate(f"(() => {{ const v = window.splatView; v.setMode('still');"
                                f" v.resize({WIDTH}, {HEIGHT}); v.canvas.style.width = '{WIDTH}px';"
                                f" v.canvas.style.height = '{HEIGHT}px';"
                                f" v.showOverlay(false); v.setIntrinsics({json.dumps(k)});"
                                f" v.setPose({json.dumps(pose)}); }})()")
            frames_before = await page.evaluate("window.splatView.frames")
            await page.wait_for(f"window.splatView.frames >= {frames_before + 5}", 60)
            await asyncio.sleep(1.0)  # Spark sorts in a worker: let the order settle
            shots = {"spz": await _canvas_shot(page)}
            fps = await page.wait_for("window.viewerState.splat.fps > 0 && window.viewerState.splat.fps", 30)
            shown_pose = await page.evaluate("window.splatView.pose()")
            readings = {"spz": await page.evaluate("window.splatView.readSplats()")}
            for fmt in ("splat", "ply"):
                await page.evaluate(f"(() => {{ const s = document.getElementById('splat-format'); s.value = '{fmt}';"
                                    " s.dispatchEvent(new Event('change')); })()")
                await page.wait_for(f"window.viewerState.splat.map && window.viewerState.splat.map.format === '{fmt}'",
                                    90)
                readings[fmt] = await page.evaluate("window.splatView.readSplats()")
                if fmt == "splat":  # exact zero third scales: Spark's own 2D-surfel path (enable2DGS)
                    frames_before = await page.evaluate("window.splatView.frames")
                    await page.wait_for(f"window.splatView.frames >= {frames_before + 5}", 60)
                    await asyncio.sleep(1.0)
                    shots["splat"] = await _canvas_shot(page)
            info = await page.evaluate("document.getElementById('splat-info').textContent")
            return {"loaded": loaded, "shots": shots, "fps": fps, "readings": readings, "info": info,
                    "pose": shown_pose, "errors": list(page.console_errors),
                    "last_error": await page.evaluate("window.viewerState.lastError")}

    result = asyncio.run(scenario())
    assert result["errors"] == [] and result["last_error"] is None, (result["errors"], result["last_error"])
    assert result["loaded"]["format"] == "spz" and result["loaded"]["splats"] == n
    assert np.allclose(result["pose"], pose, atol=1e-5)  # the page's camera is the keyframe's
    assert result["fps"] > 0 and "frames/s" in result["info"]

    # the browser's frame against the server's render of the same camera
    params = {"pose": ",".join(f"{v:.9g}" for v in pose), "width": WIDTH, "height": HEIGHT,
              **{name: k[name] * WIDTH / k["width"] for name in ("fx", "cx")},
              **{name: k[name] * HEIGHT / k["height"] for name in ("fy", "cy")}}
    server_png = httpx.get(f"{stack.url}/v1/sessions/{session.id}/render", params=params,
                           headers={"X-API-Key": KEY}, timeout=120).content
    server = cv2.imdecode(np.frombuffer(server_png, np.uint8), cv2.IMREAD_COLOR)
    (ARTIFACTS / "splats_server.png").write_bytes(server_png)
    psnr = {}
    for fmt, shot in result["shots"].items():
        browser = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
        assert browser.shape == server.shape == (HEIGHT, WIDTH, 3)
        assert browser.std() > 5, f"the browser drew a blank frame ({fmt})"
        psnr[fmt] = _psnr(browser, server)
        (ARTIFACTS / f"splats_browser_{fmt}.png").write_bytes(shot)
    (ARTIFACTS / "splats_compare.json").write_text(json.dumps({"psnr_db": psnr, "browser_fps": result["fps"],
                                                               "splats": n, "map": result["loaded"]}, indent=1))
    # spz: thin 3D Gaussians (its smallest scale is exp(-10) m); splat: Spark's 2D path (third scale exactly 0)
    assert min(psnr.values()) >= 20.0, f"browser vs server render: {psnr} dB (artifacts in {ARTIFACTS})"

    # Spark's reading of each format against the PLY's values
    for fmt, reading in result["readings"].items():
        got = {name: np.asarray(values, dtype=np.float64) for name, values in reading.items()}
        assert len(got["opacities"]) == n, fmt
        centres = got["centers"].reshape(n, 3)
        expected = reference.means.astype(np.float64) * ([1, -1, -1] if fmt == "spz" else 1)  # SPZ: right-up-back
        position_error = np.abs(centres - expected).max()
        assert position_error < 2e-3 + 1e-3 * np.abs(expected).max(), (fmt, position_error)
        colour_error = np.abs(got["colors"].reshape(n, 3) - np.clip(reference.colors, 0, 1)).max()
        assert colour_error < 0.02, (fmt, colour_error)
        assert np.abs(got["opacities"] - reference.opacities).max() < 0.02, fmt
        quats = got["quats"].reshape(n, 4)
        ref_quats = reference.quats.astype(np.float64) * ([1, 1, -1, -1] if fmt == "spz" else 1)
        normal_error = np.degrees(np.arccos(np.clip(np.abs((_normal(quats) * _normal(ref_quats)).sum(1)), 0, 1)))
        if fmt == "splat":
            # .splat stores w in a byte whose largest value reads 127/128, and Spark takes the angle from w as read:
            # a rotation within ~15 degrees of the identity (|w| > 0.99) reads up to 14 degrees off there (measured:
            # surfels the hole closing adds facing the first keyframe, the world's axes). Those are left out.
            normal_error = normal_error[np.abs(ref_quats[:, 0]) < 0.99]
        assert np.median(normal_error) < 1.0 and normal_error.max() < 5.0, (fmt, normal_error.max())
        scales = got["scales"].reshape(n, 3)
        assert np.abs(np.log(scales[:, :2] / reference.scales[:, :2])).max() < 0.1, fmt
        assert scales[:, 2].max() < 1e-4, (fmt, scales[:, 2].max())  # flat: 2D surfels stay 2D
        if fmt == "splat":
            assert scales[:, 2].max() == 0.0  # exactly: Spark draws these as oriented 2D Gaussians


def test_the_page_follows_a_streaming_session_live(chromium, stack):
    """Opened before the frames come: the map grows in the page (fetched again as keyframes arrive, the old one
    shown meanwhile), the live feed brings poses and the end, and the final map is the server's."""
    frames = icl_frames(10)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with FlashMonoClient(stack.url, api_key=KEY) as client:
        session = client.create_session(intrinsics=frames[0].intrinsics, preset="rgbd", name="splat-live",
                                        skip_frames=False)

    def stream() -> None:
        with FlashMonoClient(stack.url, api_key=KEY) as client:
            client.stream(session.id, frames, wire=WireOptions(send_depth=True, send_pose=True), max_pending=2,
                          fps=2.0)

    async def scenario() -> dict:
        async with Browser(chromium, extra_flags=WEBGL_FLAGS) as page:
            await page.navigate(f"{stack.url}/viewer?session={session.id}&api_key={KEY}")
            await page.wait_for("window.viewerState && window.viewerState.splat.ready", 60)
            streaming = asyncio.create_task(asyncio.to_thread(stream))
            await page.wait_for("window.viewerState.livePoses >= 1", 120)
            await streaming
            await page.wait_for("window.viewerState.events.some((e) => e.type === 'finished')", 120)
            await page.wait_for("window.viewerState.splat.map && window.viewerState.splat.map.key.includes('finished')",
                                120)
            await asyncio.sleep(2)
            (ARTIFACTS / "viewer_live_page.png").write_bytes(await page.screenshot())
            return {"history": await page.evaluate("window.viewerState.splat.history"),
                    "live_poses": await page.evaluate("window.viewerState.livePoses"),
                    "tracking": await page.evaluate("document.getElementById('tracking-state').textContent"),
                    "events": await page.evaluate("document.getElementById('events').textContent"),
                    "drawn": await page.evaluate("window.viewerState.posesDrawn"),
                    "errors": list(page.console_errors)}

    result = asyncio.run(scenario())
    # A worker busy mapping may answer a map request late (504/503; the page tries again at its next poll); nothing
    # else may fail.
    transient = ("503 (Service Unavailable)", "504 (Gateway Timeout)")
    assert [e for e in result["errors"] if not (any(t in e for t in transient) and "/map?format=" in e)] == [], \
        result["errors"]
    with FlashMonoClient(stack.url, api_key=KEY) as client:
        final = splat_arrays_from_ply(client.download_map(session.id))
    history = result["history"]
    assert len(history) >= 2, history  # the map came again as the session went on, not once at the end
    assert history[0]["splats"] < history[-1]["splats"] == len(final), history
    # none asked for while the session finished: such a request waits out the final refinement
    assert not any("|finishing|" in h["key"] for h in history), history
    assert result["live_poses"] >= 1 and result["drawn"] == len(frames)
    assert result["tracking"] == "tracking: finished" and "finished" in result["events"]


def test_flashmono_export_writes_each_format_of_a_real_map(mapped_session, tmp_path: Path) -> None:
    import subprocess

    from worker.mapping.splat_file import decode_splat
    from worker.mapping.spz import decode_spz

    stack, session, ply = mapped_session
    reference = splat_arrays_from_ply(ply)
    env = {**os.environ, "FLASHMONO_SERVER": stack.url, "FLASHMONO_API_KEY": KEY, "PYTHONPATH": str(REPO)}
    for args, name in ((["--format", "spz"], "map.spz"), (["--out", str(tmp_path / "room.splat")], "room.splat")):
        run = subprocess.run([sys.executable, "-m", "client.cli", "export", session.id, *args], cwd=tmp_path, env=env,
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
        data = (tmp_path / name).read_bytes()
        decoded = decode_spz(data) if name.endswith(".spz") else decode_splat(data)
        assert len(decoded) == len(reference) and np.abs(decoded.means - reference.means).max() < 1e-3
        assert f"wrote {len(data)} bytes ({name.rsplit('.', 1)[1]})" in run.stderr
