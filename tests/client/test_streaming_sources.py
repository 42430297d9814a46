"""Frame sources for streaming and the binary frame message a phone sends."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from client.streaming import WireOptions, encode_depth_png, encode_frame_message, open_frames
from protocol.codec import unpack
from worker.data.frame import Frame
from worker.geometry import Intrinsics


def _frame(index: int = 0, with_extras: bool = True) -> Frame:
    rng = np.random.default_rng(index)
    # Smooth image so JPEG keeps it close.
    base = cv2.resize(rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), (64, 48), interpolation=cv2.INTER_CUBIC)
    depth = np.full((48, 64), 1.234, dtype=np.float32)
    depth[0, 0] = 0.0
    pose = np.eye(4)
    pose[:3, 3] = [0.1, -0.2, 0.3]
    return Frame(index=index, timestamp=index / 30, image=base,
                 intrinsics=Intrinsics(50.0, 51.0, 32.0, 24.0, 64, 48) if with_extras else None,
                 depth=depth if with_extras else None, pose=pose if with_extras else None)


def test_frame_message_round_trips_image_intrinsics_depth_and_pose() -> None:
    frame = _frame(3)
    message = unpack(encode_frame_message(frame, seq=5, options=WireOptions(send_depth=True, send_pose=True)))
    assert message["type"] == "frame" and message["seq"] == 5
    assert message["timestamp"] == pytest.approx(0.1)
    assert message["image"][:2] == b"\xff\xd8"  # JPEG
    decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(message["image"], np.uint8), cv2.IMREAD_COLOR),
                           cv2.COLOR_BGR2RGB)
    assert np.abs(decoded.astype(int) - frame.image.astype(int)).mean() < 4
    assert message["intrinsics"] == {"fx": 50.0, "fy": 51.0, "cx": 32.0, "cy": 24.0}
    depth_mm = cv2.imdecode(np.frombuffer(message["depth"], np.uint8), cv2.IMREAD_UNCHANGED)
    assert depth_mm.dtype == np.uint16 and depth_mm[1, 1] == 1234 and depth_mm[0, 0] == 0
    assert np.allclose(np.array(message["pose"]).reshape(4, 4), frame.pose)


def test_depth_and_pose_are_only_sent_when_asked() -> None:
    message = unpack(encode_frame_message(_frame(), seq=0))
    assert "depth" not in message and "pose" not in message and "intrinsics" in message
    bare = unpack(encode_frame_message(_frame(with_extras=False), seq=1,
                                       options=WireOptions(send_depth=True, send_pose=True)))
    assert set(bare) == {"type", "seq", "timestamp", "image"}


def test_depth_png_clips_and_cleans_invalid_values() -> None:
    depth = np.array([[np.nan, -1.0], [70.0, 0.0015]], dtype=np.float32)
    mm = cv2.imdecode(np.frombuffer(encode_depth_png(depth), np.uint8), cv2.IMREAD_UNCHANGED)
    assert mm.tolist() == [[0, 0], [65535, 2]]


def test_bad_jpeg_quality_is_refused() -> None:
    with pytest.raises(ValueError, match="quality"):
        encode_frame_message(_frame(), 0, WireOptions(jpeg_quality=0))


def test_iterables_of_frames_honour_stride_and_max_frames() -> None:
    frames = [_frame(i, with_extras=False) for i in range(10)]
    picked = list(open_frames(frames, stride=3, max_frames=3))
    assert [f.index for f in picked] == [0, 3, 6]
    with pytest.raises(ValueError, match="Frame"):
        list(open_frames([1, 2, 3]))
    with pytest.raises(ValueError, match="stride"):
        open_frames(frames, stride=0)


def test_webcam_sources_are_parsed_and_a_missing_camera_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="webcam:0"):
        open_frames("webcam:zero")
    with pytest.raises(ValueError, match="could not open webcam 97"):
        list(open_frames("webcam:97", max_frames=1))


def test_paths_go_through_the_dataset_readers(data_dir: Path) -> None:
    import worker.data

    if not hasattr(worker.data, "open_source"):
        pytest.skip("worker.data.open_source has not landed yet")
    frames = list(open_frames(data_dir / "icl_mini", max_frames=3, stride=2))
    assert len(frames) == 3
    assert frames[0].image.shape == (240, 320, 3)
    assert frames[1].timestamp > frames[0].timestamp
