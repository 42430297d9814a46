"""In-process units of the gateway: image headers, frame validation, API key configuration, TUM output."""

from __future__ import annotations

import json

import cv2
import msgpack
import numpy as np
import pytest

from protocol.image_header import image_size
from service.frame_validation import FrameRejected, check_frame_message
from service.routes_results import tum_text
from service.settings import Settings, load_api_keys_file, parse_api_keys


def encode(ext: str, shape=(37, 53, 3)) -> bytes:
    return cv2.imencode(ext, np.zeros(shape, np.uint8))[1].tobytes()


def test_image_size_reads_jpeg_and_png_headers():
    assert image_size(encode(".jpg")) == ("jpeg", 53, 37)
    assert image_size(encode(".png", (20, 10))) == ("png", 10, 20)
    progressive = cv2.imencode(".jpg", np.zeros((9, 7, 3), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1]
    assert image_size(progressive.tobytes()) == ("jpeg", 7, 9)
    for bad in (b"", b"GIF89a", b"\xff\xd8\xff\xe0\x00", encode(".png")[:20], b"\xff\xd8" + b"\x00" * 10):
        with pytest.raises(ValueError):
            image_size(bad)


def test_frame_validation_messages():
    jpeg = encode(".jpg", (240, 320, 3))
    ok = check_frame_message(msgpack.packb({"type": "frame", "seq": 3, "timestamp": 0.1, "image": jpeg}),
                             1 << 20, None)
    assert (ok.seq, ok.width, ok.height) == (3, 320, 240)
    with pytest.raises(FrameRejected, match="exceeds the limit") as err:
        check_frame_message(b"\x00" * 2048, 1024, None)
    assert err.value.code == "too_large"
    with pytest.raises(FrameRejected) as err:
        check_frame_message(msgpack.packb({"type": "frame", "seq": True, "timestamp": 0, "image": jpeg}), 1 << 20,
                            None)
    assert err.value.code == "bad_message"
    with pytest.raises(FrameRejected) as err:
        check_frame_message(msgpack.packb({"type": "frame", "seq": 1, "timestamp": float("nan"), "image": jpeg}),
                            1 << 20, None)
    assert err.value.code == "bad_message" and err.value.seq == 1


def test_api_key_configuration(tmp_path):
    keys = parse_api_keys("a=stream,read; b=admin ;")
    assert keys == {"a": {"stream", "read"}, "b": {"admin"}}
    for bad in ("a", "a=", "a=write", "=read"):
        with pytest.raises(ValueError):
            parse_api_keys(bad)
    path = tmp_path / "keys.json"
    path.write_text(json.dumps({"k": ["read"]}))
    assert load_api_keys_file(path) == {"k": {"read"}}
    settings = Settings.from_env({"FLASHMONO_API_KEYS": "x=stream", "FLASHMONO_API_KEYS_FILE": str(path),
                                  "REDIS_URL": "redis://h:1/0"})
    assert settings.auth_enabled and set(settings.api_keys) == {"x", "k"} and settings.redis_url == "redis://h:1/0"
    assert not Settings.from_env({}).auth_enabled
    with pytest.raises(ValueError):
        Settings.from_env({"FLASHMONO_MAX_QUEUE": "0"})


def test_tum_text_removes_the_scale_of_a_sim3_pose():
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = 2.0 * rot
    pose[:3, 3] = [1, 2, 3]
    line = tum_text([{"seq": 0, "timestamp": 0.5, "pose": pose.reshape(-1).tolist()}]).splitlines()[1]
    values = [float(v) for v in line.split()]
    assert values[:4] == pytest.approx([0.5, 1, 2, 3])
    assert values[4:] == pytest.approx([0, 0, np.sin(angle / 2), np.cos(angle / 2)], abs=1e-7)
