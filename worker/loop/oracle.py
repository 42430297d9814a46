"""A ground-truth model double: answers `init_state`/`step` like FeedForwardModel from RGB-D frames and poses.

It lets the tracker and loop closure run end to end where the learned model is absent or untrained (tests,
benchmarks of the loop-closure back end). Like a monocular model it predicts each submap in its own frame (the
submap's first camera) and its own scale (1 / median depth of the first frame), and it can inject drift: a
rotation bias per frame inside a submap, so chaining submaps drifts like real odometry. A step with a past state
and update=False relocalizes the frame in that past submap, as in paper 4.2.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from worker.frontend.types import HiddenState, StepOutput
from worker.geometry import Intrinsics, make_sim3, project_points, quat_to_rotmat, sim3_apply, so3_exp, unproject_depth


@dataclass
class OracleFrame:
    image: torch.Tensor  # [1,3,H,W] float in [0,1]
    depth: torch.Tensor  # [H,W] metres, 0 = invalid
    pose: torch.Tensor  # [4,4] float64 c2w ground truth
    intrinsics: Intrinsics


def load_rgbd_folder(path: str | Path, stride: int = 1, downscale: int = 1) -> list[OracleFrame]:
    """Frames of a folder with rgb/*.jpg, depth/*.png (mm), groundtruth.txt (TUM c2w) and intrinsics.json.

    `stride` keeps every n-th frame; `downscale` shrinks images (area) and depth (nearest) by an integer factor."""
    path = Path(path)
    meta = json.loads((path / "intrinsics.json").read_text())
    intr = Intrinsics(meta["fx"], meta["fy"], meta["cx"], meta["cy"], meta["width"], meta["height"])
    rows = [line.split() for line in (path / "groundtruth.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    rgb_files = sorted((path / "rgb").glob("*.jpg"))
    if len(rgb_files) != len(rows):
        raise ValueError(f"{path}: {len(rgb_files)} images but {len(rows)} poses")
    if downscale > 1:
        intr = intr.scaled(intr.width // downscale, intr.height // downscale)
    frames = []
    for rgb_file, row in list(zip(rgb_files, rows))[::stride]:
        bgr = cv2.imread(str(rgb_file), cv2.IMREAD_COLOR)
        depth = cv2.imread(str(path / "depth" / (rgb_file.stem + ".png")), cv2.IMREAD_UNCHANGED)
        if bgr is None or depth is None:
            raise ValueError(f"cannot read frame {rgb_file.stem} in {path}")
        if downscale > 1:
            size = (bgr.shape[1] // downscale, bgr.shape[0] // downscale)
            bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            depth = depth[downscale // 2::downscale, downscale // 2::downscale][:size[1], :size[0]]
        image = torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).permute(2, 0, 1)[None].float() / 255.0
        tx, ty, tz, qx, qy, qz, qw = (float(v) for v in row[1:8])
        R = quat_to_rotmat(torch.tensor([qw, qx, qy, qz], dtype=torch.float64))
        pose = make_sim3(R, torch.tensor([tx, ty, tz], dtype=torch.float64))
        frames.append(OracleFrame(image, torch.from_numpy(depth.astype(np.float32) / meta["depth_scale"]), pose,
                                  intr))
    return frames


def ground_truth_overlap(frames, i: int, j: int, depth_tolerance: float = 0.1) -> float:
    """Fraction of frame i's depth points seen by frame j with a consistent depth (from ground truth)."""
    K = frames[i].intrinsics.matrix(torch.float64)
    d = frames[i].depth.double()
    P = unproject_depth(d, K)[d > 0][::4]
    Pj = sim3_apply(torch.linalg.inv(frames[j].pose), sim3_apply(frames[i].pose, P))
    uv, z = project_points(Pj, K)
    H, W = frames[j].depth.shape
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    zj = frames[j].depth.double()[uv[inside, 1].long(), uv[inside, 0].long()]
    good = (zj > 0) & ((z[inside] - zj).abs() < depth_tolerance * zj)
    return float(good.sum()) / max(1, len(P))


def _fingerprint(image: torch.Tensor) -> str:
    return hashlib.sha1(image.detach().cpu().contiguous().numpy().tobytes()).hexdigest()


class OracleModel:
    """`init_state`/`step` from ground truth. State tokens hold (first frame, scale, frames seen) of the submap."""

    def __init__(self, frames: list[OracleFrame], rotation_drift: float = 0.0, point_noise: float = 0.0,
                 seed: int = 0) -> None:
        self.frames = frames
        self.rotation_drift = rotation_drift
        self.point_noise = point_noise
        self.generator = torch.Generator().manual_seed(seed)
        self._by_image = {_fingerprint(f.image): n for n, f in enumerate(frames)}
        self.calls = 0

    def init_state(self, batch: int = 1) -> HiddenState:
        return HiddenState(torch.full((batch, 1, 3), -1.0), torch.zeros(batch, 1, 2), 0)

    def frame_index(self, image: torch.Tensor) -> int:
        n = self._by_image.get(_fingerprint(image))
        if n is None:
            raise ValueError("OracleModel was given an image it does not know")
        return n

    def _camera_points(self, n: int, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.frames[n]
        depth = f.depth.clone()
        valid = depth > 0
        depth[~valid] = depth[valid].median() if valid.any() else 1.0
        pts = unproject_depth(depth, f.intrinsics.matrix()) * scale
        if self.point_noise:
            pts = pts * (1 + self.point_noise * torch.randn(pts.shape[:2] + (1,), generator=self.generator))
        conf = torch.where(valid, torch.full_like(depth, 10.0), torch.ones_like(depth))
        return pts, conf

    def step(self, image: torch.Tensor, state: HiddenState, update: bool = True) -> StepOutput:
        self.calls += 1
        n = self.frame_index(image)
        first, scale, seen = (float(v) for v in state.state_tokens[0, 0])
        if first < 0:
            d = self.frames[n].depth
            first, scale, seen = float(n), float(1.0 / d[d > 0].median()), 0.0
        rel = torch.linalg.inv(self.frames[int(first)].pose) @ self.frames[n].pose
        drift = so3_exp(torch.tensor([0.0, self.rotation_drift * seen, 0.0], dtype=torch.float64))
        pose = make_sim3(drift @ rel[:3, :3], rel[:3, 3] * scale).float()
        pts, conf = self._camera_points(n, scale)
        H, W = pts.shape[:2]
        new_state = state
        if update:
            new_state = HiddenState(torch.tensor([[[first, scale, seen + 1]]]), state.pose_memory.clone(),
                                    state.frames_seen + 1)
        quats = torch.zeros(H, W, 4)
        quats[..., 0] = 1.0
        return StepOutput(
            pose_c2w=pose[None], points_cam=pts[None].float(), conf=conf[None],
            points_world=(pts @ pose[:3, :3].T + pose[:3, 3])[None].float(), conf_world=conf[None],
            opacity=torch.full((1, H, W), 0.9), quats=quats[None],
            scales=(pts[..., 2:3].expand(H, W, 2) / self.frames[n].intrinsics.fx)[None].float(),
            colors=image[0].permute(1, 2, 0)[None].float(), state=new_state,
        )
