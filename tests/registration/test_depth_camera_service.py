"""Through the real stack (gateway, a worker with the SLAM engine, Redis): a session declares its depth camera (bad
extrinsics get a 422 with the reason), a session streaming misregistered depth without one gets a
`depth_misregistered` message and a warning in its record, and a seeded session whose device poses jump gets a
`device_pose_jump` message while its poses do not jump."""

from __future__ import annotations

from pathlib import Path

import cv2
import httpx
import msgpack
import numpy as np
import pytest
from live_stack import receive_until
from registration_scene import render, rig
from websockets.sync.client import connect

from service.launcher import LocalStack

ICL = Path(__file__).parents[1] / "data" / "icl_mini"
ROTATION = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
DEPTH_INTRINSICS = {"fx": 212.0, "fy": 211.0, "cx": 78.5, "cy": 62.0, "width": 160, "height": 120}


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_TORCH_THREADS": "1", "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=env) as running:
        yield running


@pytest.fixture(scope="module")
def api(stack):
    with httpx.Client(base_url=stack.base_url, timeout=60) as client:
        yield client


def _message(seq: int, image: np.ndarray, depth: np.ndarray, pose: np.ndarray | None = None) -> bytes:
    message = {"type": "frame", "seq": seq, "timestamp": seq / 30,
               "image": cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1].tobytes(),
               "depth": cv2.imencode(".png", np.round(depth * 1000).astype(np.uint16))[1].tobytes()}
    if pose is not None:
        message["pose"] = pose.reshape(-1).tolist()
    return msgpack.packb(message, use_bin_type=True)


def _stream(stack, sid: str, messages: list[bytes]) -> list[dict]:
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
        for message in messages:
            ws.send(message)
        return receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == len(messages) - 1, timeout_s=180)


@pytest.mark.parametrize("depth_camera, reason", [
    ({"rotation": ROTATION, "translation": [52.0, 0.0, 0.0]}, "metres"),
    ({"rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], "translation": [0.05, 0.0, 0.0]},
     "reflection"),
    ({"rotation": ROTATION}, "translation"),
    ({"depth_to_color": [[1.0, 0.0, 0.0, 0.05], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]}, "4x4"),
    ({"depth_to_color": [[1.0, 0.1, 0.0, 0.05], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1]]},
     "orthonormal"),
])
def test_bad_extrinsics_are_refused_with_the_reason(api, depth_camera, reason) -> None:
    response = api.post("/v1/sessions", json={"depth_camera": {"intrinsics": DEPTH_INTRINSICS, **depth_camera}})
    assert response.status_code == 422
    assert reason in str(response.json()["detail"]), response.json()


def test_a_declared_depth_camera_is_kept_with_the_session(api) -> None:
    body = {"intrinsics": DEPTH_INTRINSICS, "rotation": ROTATION, "translation": [0.05, 0.0, 0.0]}
    created = api.post("/v1/sessions", json={"depth_camera": body, "pose_mode": "seeded"})
    assert created.status_code == 201, created.text
    session = api.get(f"/v1/sessions/{created.json()['id']}").json()
    assert session["pose_mode"] == "seeded" and session["warnings"] == []
    assert session["depth_camera"]["depth_to_color"] == [[1.0, 0.0, 0.0, 0.05], [0.0, 1.0, 0.0, 0.0],
                                                         [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def test_misregistered_depth_is_reported_to_the_client_and_in_the_session(stack, api) -> None:
    colour, depth_camera, depth_to_colour = rig()
    messages = []
    for k in range(6):  # the rig slides sideways 1 cm per frame; depth as the depth camera sees it
        pose = np.eye(4)
        pose[0, 3] = 0.01 * k
        image, _ = render(colour, pose)
        _, raw = render(depth_camera, pose @ depth_to_colour)
        messages.append(_message(k, image, raw))
    camera = {"fx": colour.fx, "fy": colour.fy, "cx": colour.cx, "cy": colour.cy, "width": 160, "height": 120}
    sid = api.post("/v1/sessions", json={"intrinsics": camera, "preset": "fast"}).json()["id"]
    received = _stream(stack, sid, messages)
    notices = [m for m in received if m["type"] == "depth_misregistered"]
    assert len(notices) == 1 and (notices[0]["shift_dx"], notices[0]["shift_dy"]) != (0, 0)
    warnings = api.get(f"/v1/sessions/{sid}").json()["warnings"]
    assert len(warnings) == 1 and "depth_camera" in warnings[0]


def test_a_device_pose_jump_is_reported_and_not_followed(stack, api) -> None:
    from worker.data import open_source

    frames = list(open_source(str(ICL), max_frames=8, resize=(160, 120), use_gt_depth=True,
                              use_gt_poses=True))
    jump = np.eye(4)
    jump[:3, 3] = [0.2, 0.0, 0.05]
    messages = [_message(f.index, f.image, f.depth, jump @ f.pose if f.index >= 5 else f.pose) for f in frames]
    camera = frames[0].intrinsics.to_dict()
    sid = api.post("/v1/sessions", json={"intrinsics": camera, "preset": "fast", "pose_mode": "seeded"}).json()["id"]
    received = _stream(stack, sid, messages)
    jumps = [m for m in received if m["type"] == "device_pose_jump"]
    assert [m["seq"] for m in jumps] == [5] and jumps[0]["translation"] > 0.15
    poses = {m["seq"]: np.reshape(m["pose"], (4, 4)) for m in received if m["type"] == "pose"}
    steps = [np.linalg.norm(poses[k + 1][:3, 3] - poses[k][:3, 3]) for k in range(7)]
    true_steps = [np.linalg.norm(frames[k + 1].pose[:3, 3] - frames[k].pose[:3, 3]) for k in range(7)]
    assert max(abs(s - t) for s, t in zip(steps, true_steps)) < 0.03
