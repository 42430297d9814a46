"""Helpers for the service tests: ICL frames as wire messages, and reading the server's stream messages."""

from __future__ import annotations

from pathlib import Path

import cv2
import msgpack
import numpy as np
import torch
from live_stack import receive_until  # noqa: F401  (re-exported for this area's tests)

from worker.geometry import quat_to_rotmat

ICL_DIR = Path(__file__).resolve().parent.parent / "data" / "icl_mini"
ICL_INTRINSICS = {"fx": 262.5, "fy": 262.5, "cx": 159.75, "cy": 119.75, "width": 320, "height": 240}


def icl_frames(count: int, scale: float = 1.0) -> list[dict]:
    """The first `count` ICL frames: {jpeg, depth_png, pose (16 floats), timestamp}, optionally downscaled."""
    rows = [line.split() for line in (ICL_DIR / "groundtruth.txt").read_text().splitlines()
            if line and not line.startswith("#")]
    names = sorted(p.stem for p in (ICL_DIR / "rgb").glob("*.jpg"))[:count]
    frames = []
    for name, row in zip(names, rows):
        bgr = cv2.imread(str(ICL_DIR / "rgb" / f"{name}.jpg"))
        depth = cv2.imread(str(ICL_DIR / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        if scale != 1.0:
            size = (round(bgr.shape[1] * scale), round(bgr.shape[0] * scale))
            bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        values = np.array(row[1:], dtype=np.float64)
        pose = np.eye(4)
        qx, qy, qz, qw = values[3:]
        pose[:3, :3] = quat_to_rotmat(torch.tensor([qw, qx, qy, qz], dtype=torch.float64)).numpy()
        pose[:3, 3] = values[:3]
        frames.append({"jpeg": cv2.imencode(".jpg", bgr)[1].tobytes(),
                       "depth": cv2.imencode(".png", depth)[1].tobytes(),
                       "pose": pose.reshape(-1).tolist(), "timestamp": float(row[0])})
    return frames


def frame_message(seq: int, frame: dict, with_pose: bool = False, with_depth: bool = False, **extra) -> bytes:
    message = {"type": "frame", "seq": seq, "timestamp": frame["timestamp"], "image": frame["jpeg"], **extra}
    if with_pose:
        message["pose"] = frame["pose"]
    if with_depth:
        message["depth"] = frame["depth"]
    return msgpack.packb(message, use_bin_type=True)


def of_type(messages: list[dict], kind: str) -> list[dict]:
    return [m for m in messages if m.get("type") == kind]
