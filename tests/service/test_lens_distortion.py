"""Cameras as they come, through the real stack (gateway, a SLAM worker, Redis): the Kinect's raw frames, lens
distortion and all, streamed with its published calibration in the session's intrinsics (as openapi.yaml documents
it, no preset) are tracked against the motion capture, and the session renders in the pinhole camera its frames were
undistorted to; a lens that folds the image is a 422 with the reason; a frame whose own distortion is bad gets an
error frame and the session goes on."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest
from live_stack import receive_until
from websockets.sync.client import connect

from service.launcher import LocalStack
from worker.data.tum_trajectory import read_tum
from worker.eval.metrics import absolute_trajectory_error
from worker.runtime.frames import session_camera

RAW = Path(__file__).parents[1] / "data" / "tum_fr1_xyz_raw_mini"
CALIBRATION = json.loads((RAW / "intrinsics.json").read_text())
CAMERA = {k: CALIBRATION[k] for k in ("fx", "fy", "cx", "cy", "width", "height")}
LENS = CALIBRATION["distortion"]


@pytest.fixture(scope="module")
def stack():
    env = {"FLASHMONO_ENGINE": "slam", "FLASHMONO_TORCH_THREADS": "1", "FLASHMONO_LOG_LEVEL": "WARNING"}
    with LocalStack(workers=1, worker_env=env) as running:
        yield running


@pytest.fixture(scope="module")
def api(stack):
    with httpx.Client(base_url=stack.base_url, timeout=60) as client:
        yield client


def _ground_truth() -> np.ndarray:
    return read_tum(RAW / "groundtruth.txt").poses


def _messages(intrinsics: dict | None = None, at: int | None = None) -> list[bytes]:
    """The raw frames as wire messages (RGB-D); frame `at` carries `intrinsics` of its own."""
    messages = []
    for seq, image in enumerate(sorted((RAW / "rgb").glob("*.jpg"))):
        message = {"type": "frame", "seq": seq, "timestamp": seq / 15.0, "image": image.read_bytes(),
                   "depth": (RAW / "depth" / f"{image.stem}.png").read_bytes()}
        if seq == at:
            message["intrinsics"] = intrinsics
        messages.append(msgpack.packb(message, use_bin_type=True))
    return messages


def _stream(stack, sid: str, messages: list[bytes]) -> list[dict]:
    with connect(f"{stack.ws_url}/v1/sessions/{sid}/stream", open_timeout=30) as ws:
        for message in messages:
            ws.send(message)
        return receive_until(ws, lambda m: m["type"] == "pose" and m["seq"] == len(messages) - 1, timeout_s=180)


def _ate_cm(received: list[dict]) -> float:
    poses = {m["seq"]: np.reshape(m["pose"], (4, 4)) for m in received if m["type"] == "pose"}
    truth = _ground_truth()
    seqs = sorted(poses)
    estimate = np.stack([poses[s] for s in seqs])
    return 100 * absolute_trajectory_error(estimate, np.stack([truth[s] for s in seqs]), align="se3").rmse


@pytest.mark.parametrize("distortion, reason", [
    ({"model": "radtan", "k1": -0.9}, "folds"),
    ({"model": "fisheye", "k1": 0.01, "p1": 0.001}, "unknown: p1"),
])
def test_a_lens_that_cannot_be_is_refused_with_the_reason(api, distortion, reason) -> None:
    response = api.post("/v1/sessions", json={"intrinsics": {**CAMERA, "distortion": distortion}})
    assert response.status_code == 422
    assert reason in str(response.json()["detail"]), response.json()


def test_raw_kinect_frames_with_their_lens_track_and_render_as_the_pinhole_camera(stack, api) -> None:
    declared = {**CAMERA, "distortion": LENS}
    sid = api.post("/v1/sessions", json={"intrinsics": declared}).json()["id"]
    with_lens = _ate_cm(_stream(stack, sid, _messages()))
    session = api.get(f"/v1/sessions/{sid}").json()
    assert session["intrinsics"]["distortion"] == LENS
    pinhole = session_camera(declared).scaled(320, 240)
    used = session["estimated_intrinsics"]
    assert (used["width"], used["height"]) == (320, 240)
    assert all(abs(used[k] - getattr(pinhole, k)) < 1e-6 for k in ("fx", "fy", "cx", "cy"))
    view = api.get(f"/v1/sessions/{sid}/render", params={"pose": ",".join(["1", "0", "0", "0", "0", "1", "0", "0",
                                                                          "0", "0", "1", "0", "0", "0", "0", "1"])})
    assert view.status_code == 200, view.text

    unsaid = api.post("/v1/sessions", json={"intrinsics": CAMERA}).json()["id"]
    without_lens = _ate_cm(_stream(stack, unsaid, _messages()))
    print(f"ATE with the lens {with_lens:.2f} cm, without {without_lens:.2f} cm")
    assert with_lens < 1.5, (with_lens, without_lens)
    assert with_lens < without_lens, (with_lens, without_lens)


def test_a_frame_with_a_bad_lens_gets_an_error_and_the_session_goes_on(stack, api) -> None:
    sid = api.post("/v1/sessions", json={"intrinsics": {**CAMERA, "distortion": LENS}}).json()["id"]
    folding = {"fx": 258.65, "fy": 258.23, "cx": 159.3, "cy": 127.7, "distortion": {"k1": -0.9}}
    received = _stream(stack, sid, _messages(folding, at=3)[:8])
    errors = [m for m in received if m["type"] == "error"]
    assert [(m["code"], m.get("seq")) for m in errors] == [("bad_intrinsics", 3)]
    assert "folds" in errors[0]["message"]
    assert sorted(m["seq"] for m in received if m["type"] == "pose") == [0, 1, 2, 4, 5, 6, 7]


def test_the_cli_streams_a_raw_camera_with_its_calibration_file(stack, api, tmp_path, capsys) -> None:
    """`flashmono stream FOLDER --camera calibration.json`: the SDK creates the session with the lens, sends the
    images as taken (no per-frame intrinsics), and the worker undistorts them."""
    from client.cli import main

    calibration = tmp_path / "camera.json"
    calibration.write_text(json.dumps({**CAMERA, "distortion": LENS}))
    status = main(["stream", str(RAW / "rgb"), "--server", stack.base_url, "--camera", str(calibration),
                   "--max-frames", "12", "--quiet"])
    assert status == 0
    sid = capsys.readouterr().out.strip().splitlines()[-1]
    session = api.get(f"/v1/sessions/{sid}").json()
    assert session["intrinsics"]["distortion"] == LENS and session["frames_processed"] == 12
    pinhole = session_camera({**CAMERA, "distortion": LENS}).scaled(320, 240)
    assert abs(session["estimated_intrinsics"]["fx"] - pinhole.fx) < 1e-6


def test_the_cli_refuses_a_calibration_file_that_is_not_one(stack, tmp_path, capsys) -> None:
    from client.cli import main

    calibration = tmp_path / "camera.json"
    calibration.write_text("[1, 2, 3]")
    assert main(["stream", str(RAW / "rgb"), "--server", stack.base_url, "--camera", str(calibration)]) != 0
    assert "expected an object" in capsys.readouterr().err
