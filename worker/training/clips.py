"""Training clips: sequences with RGB, depth and poses, fitted to the model's resolution and cut into clips."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from worker.data.frame import Frame
from worker.geometry import Intrinsics, sim3_inverse


@dataclass
class Clip:
    """L consecutive frames at the model resolution (batch of one).

    images [L,1,H,W,3] in [0,1]; depths [L,1,H,W] metres (0 = invalid); c2w [L,1,4,4] relative to the first frame;
    K [3,3].
    """

    images: torch.Tensor
    depths: torch.Tensor
    c2w: torch.Tensor
    K: torch.Tensor

    def __len__(self) -> int:
        return self.images.shape[0]

    def chw(self, t: int) -> torch.Tensor:
        """Frame t as the model's input [1,3,H,W]."""
        return self.images[t].permute(0, 3, 1, 2).contiguous()


def fit_frame(frame: Frame, width: int, height: int) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """Resize a frame to cover width x height (aspect kept), then centre-crop; intrinsics follow."""
    if frame.depth is None or frame.intrinsics is None or frame.gt_pose is None:
        raise ValueError(f"training frame {frame.index} needs depth, intrinsics and a ground-truth pose")
    h0, w0 = frame.image.shape[:2]
    scale = max(width / w0, height / h0)
    rw, rh = max(width, round(w0 * scale)), max(height, round(h0 * scale))
    image = cv2.resize(frame.image, (rw, rh), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    depth = cv2.resize(frame.depth.astype(np.float32), (rw, rh), interpolation=cv2.INTER_NEAREST)
    left, top = (rw - width) // 2, (rh - height) // 2
    intr = frame.intrinsics.scaled(rw, rh).cropped(left, top, width, height)
    return image[top:top + height, left:left + width], depth[top:top + height, left:left + width], intr


class SequenceBank:
    """Whole sequences held in memory at the model resolution (images as uint8); clips are drawn at random."""

    def __init__(self, width: int, height: int, seed: int = 0) -> None:
        self.width, self.height = width, height
        self.sequences: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = []
        self.rng = np.random.default_rng(seed)

    def add(self, frames: Iterable[Frame]) -> None:
        """Fit and store one sequence (frames must carry depth, intrinsics and ground-truth poses)."""
        images, depths, poses, K = [], [], [], None
        for frame in frames:
            image, depth, intr = fit_frame(frame, self.width, self.height)
            images.append(torch.from_numpy(np.ascontiguousarray(image)))
            depths.append(torch.from_numpy(np.ascontiguousarray(depth)))
            poses.append(torch.from_numpy(np.asarray(frame.gt_pose, dtype=np.float64)))
            K = intr.matrix()
        if len(images) < 2:
            raise ValueError("a training sequence needs at least 2 frames")
        self.add_tensors(torch.stack(images), torch.stack(depths), torch.stack(poses), K)

    def add_tensors(self, images: torch.Tensor, depths: torch.Tensor, c2w: torch.Tensor, K) -> None:
        """Store one sequence already at the bank's resolution: images uint8 [L,H,W,3], depths [L,H,W] metres,
        c2w [L,4,4], K [3,3]."""
        L = images.shape[0]
        if images.dtype != torch.uint8 or images.shape[1:] != (self.height, self.width, 3):
            raise ValueError(f"images must be uint8 [L,{self.height},{self.width},3], got {images.dtype} "
                             f"{tuple(images.shape)}")
        if depths.shape != (L, self.height, self.width) or c2w.shape != (L, 4, 4):
            raise ValueError(f"depths {tuple(depths.shape)} / poses {tuple(c2w.shape)} do not match {L} images")
        if L < 2:
            raise ValueError("a training sequence needs at least 2 frames")
        self.sequences.append((images, depths.float(), c2w.double(), torch.as_tensor(K, dtype=torch.float32)))

    def sample(self, length: int, max_gap: int = 2) -> Clip:
        """A random clip of `length` frames (consecutive frames at a random stride of 1..max_gap)."""
        if not self.sequences:
            raise ValueError("the sequence bank is empty")
        if max_gap < 1:
            raise ValueError(f"max_gap must be at least 1, got {max_gap}")
        images, depths, poses, K = self.sequences[self.rng.integers(len(self.sequences))]
        n = images.shape[0]
        gap = int(self.rng.integers(1, max_gap + 1))
        while gap > 1 and (length - 1) * gap >= n:
            gap -= 1
        length = min(length, n)
        start = int(self.rng.integers(0, n - (length - 1) * gap))
        idx = torch.arange(start, start + length * gap, gap)[:length]
        c2w = sim3_inverse(poses[idx[0]]) @ poses[idx]
        return Clip(images[idx][:, None].float() / 255.0, depths[idx][:, None], c2w[:, None].float(), K)
