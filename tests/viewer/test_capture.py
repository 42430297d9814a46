"""The capture page in headless Chromium with a fake camera fed from a real video (the bundled ICL frames as a
Y4M file): it asks for the camera, creates a session with the focal length the user typed, streams JPEG frames
over the WebSocket contract with the acks' flow control, and the real engine receives and tracks them."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import cv2
import numpy as np
from live_stack import LiveStack

from client.sdk import FlashMonoClient

sys.path.insert(0, str(Path(__file__).parent))
from cdp import Browser  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
KEY = "phone"
FPS = 5


def write_y4m(path: Path, frames: list[np.ndarray], fps: int) -> None:
    """An uncompressed YUV4MPEG2 (4:2:0) video of BGR `frames`, what Chromium's fake camera plays."""
    height, width = frames[0].shape[:2]
    with path.open("wb") as out:
        out.write(f"YUV4MPEG2 W{width} H{height} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for frame in frames:
            out.write(b"FRAME\n" + cv2.cvtColor(frame, cv2.COLOR_BGR2YUV_I420).tobytes())


def test_capture_page_streams_the_camera_and_the_session_tracks_it(chromium, tmp_path: Path) -> None:
    rgb = sorted((REPO / "tests" / "data" / "icl_mini" / "rgb").glob("*.jpg"))
    frames = [cv2.imread(str(p)) for p in rgb]
    frames += frames[::-1]  # there and back: the fake camera loops without a jump
    video = tmp_path / "icl.y4m"
    write_y4m(video, frames, FPS)
    flags = ["--use-fake-device-for-media-stream", f"--use-file-for-fake-video-capture={video}",
             "--use-fake-ui-for-media-stream", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
    with LiveStack(workers=1, api_keys=f"{KEY}=stream", engine="slam",
                   extra_env={"FLASHMONO_LOG_LEVEL": "WARNING"}) as stack:

        async def scenario() -> dict:
            async with Browser(chromium, extra_flags=flags) as page:
                await page.navigate(f"{stack.url}/viewer/capture#api_key={KEY}")
                await page.wait_for("window.captureState !== undefined", 30)
                await page.evaluate(f"(() => {{ document.getElementById('fps').value = '{FPS}';"
                                    " document.getElementById('focal').value = '262.5';"
                                    " document.getElementById('start').click(); })()")
                await page.wait_for("window.captureState.poses >= 20 || window.captureState.error", 240)
                await page.evaluate("document.getElementById('stop').click()")
                await page.wait_for("window.captureState.finished || window.captureState.error", 240)
                state = await page.evaluate("window.captureState")
                return {"state": state, "errors": list(page.console_errors),
                        "address": await page.evaluate("location.href")}

        result = asyncio.run(scenario())
        state = result["state"]
        assert state["error"] is None, state["error"]
        assert result["errors"] == [], result["errors"]
        assert "api_key" not in result["address"]
        assert state["camera"]["width"] == 320 and state["camera"]["height"] == 240
        with FlashMonoClient(stack.url, api_key=KEY) as client:
            session = client.get_session(state["sessionId"])
            trajectory = client.trajectory(state["sessionId"])
    assert session.status == "finished" and session.device_id == "browser"
    # the page names no preset: the worker chose for a live 320x240 RGB stream on this machine, and says so
    assert session.frame_rate == FPS and session.skip_frames
    assert session.settings["decided"] == "auto" and session.preset == session.settings["preset"] == "rgbd"
    assert any(reason.startswith("input: rgb;") for reason in session.settings["reasons"])
    assert session.intrinsics["fx"] == 262.5 and session.intrinsics["width"] == 320
    # every acked frame was tracked, or skipped by a tracker behind the camera (it took a newer one; each says so)
    assert session.frames_processed + session.frames_skipped == state["acked"] and session.frames_processed >= 20
    assert state.get("skipped", 0) == session.frames_skipped
    assert state["sent"] == state["acked"] + state["refused"]
    centres = np.array([np.reshape(p.pose, (4, 4))[:3, 3] for p in trajectory.poses])
    assert len(centres) == session.frames_processed and np.isfinite(centres).all()
    path = np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()
    assert path > 0.05, f"the camera did not move in the trajectory ({path:.3f})"  # tracked, not held in place
    assert session.keyframes >= 2
