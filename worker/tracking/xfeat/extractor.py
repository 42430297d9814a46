"""Sparse XFeat keypoints and descriptors of a grey image, and mutual-nearest-neighbour matching between two sets.

Detection follows the published method (`XFeat.detectAndCompute` of verlab/accelerated_features): the keypoint
logits become a full-resolution heatmap, 5x5 non-maximum suppression keeps the peaks above a threshold, each peak is
scored by heatmap x reliability, the best `top_k` are kept and their 64-d descriptors are sampled (bicubic) from
the dense map and L2-normalised. Weights: `xfeat.safetensors` beside this file (never downloaded).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file

from .model import XFeatModel

WEIGHTS = Path(__file__).resolve().parent / "xfeat.safetensors"


@dataclass
class XFeatures:
    """Keypoints [N, 2] (x, y; pixel centres at +0.5), unit descriptors [N, 64] float32 and scores [N]."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def _sample(dense: torch.Tensor, xy: torch.Tensor, height: int, width: int, mode: str) -> torch.Tensor:
    """Values [N, C] of a map [1, C, h, w] at full-resolution pixel indices xy [N, 2] (XFeat's normalisation)."""
    grid = 2.0 * (xy / torch.tensor([width - 1, height - 1], dtype=xy.dtype)) - 1.0
    out = F.grid_sample(dense, grid.view(1, -1, 1, 2).to(dense.dtype), mode=mode, align_corners=False)
    return out[0, :, :, 0].t()


class XFeatExtractor:
    """XFeat on the CPU (or the given device), at most `top_k` keypoints per image."""

    def __init__(self, top_k: int = 1024, threshold: float = 0.05, device: str = "cpu") -> None:
        self.top_k, self.threshold, self.device = top_k, threshold, torch.device(device)
        self.net = XFeatModel()
        self.net.load_state_dict(load_file(str(WEIGHTS)))
        self.net.eval().to(self.device)

    def _dense(self, gray: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, int]:
        """The network's normalised descriptor map, keypoint heatmap (full resolution) and reliability map of a
        grey image, and the size (h, w) it ran at (multiples of 32)."""
        if gray.ndim != 2 or gray.dtype != np.uint8 or min(gray.shape) < 32:
            raise ValueError(f"XFeat takes a uint8 grey image [H, W] of at least 32x32, got {gray.dtype} "
                             f"{gray.shape}")
        height, width = gray.shape
        h, w = (height // 32) * 32, (width // 32) * 32
        x = torch.from_numpy(gray).to(self.device, torch.float32).div_(255.0)[None, None]
        if (h, w) != (height, width):
            x = F.interpolate(x, (h, w), mode="bilinear", align_corners=False)
        dense, logits, reliability = self.net(x)
        heat = F.softmax(logits, 1)[:, :64]  # 8x8 cells -> full resolution
        heat = heat.permute(0, 2, 3, 1).reshape(1, h // 8, w // 8, 8, 8).permute(0, 1, 3, 2, 4).reshape(1, 1, h, w)
        return F.normalize(dense, dim=1), heat, reliability, h, w

    @torch.inference_mode()
    def extract(self, gray: np.ndarray) -> XFeatures:
        """Keypoints and descriptors of a uint8 grey image [H, W] (at least 32 x 32)."""
        return self.extract_with_map(gray)[0]

    @torch.inference_mode()
    def extract_with_map(self, gray: np.ndarray) -> tuple[XFeatures, DescriptorMap]:
        """Keypoints and descriptors of a uint8 grey image, and its dense descriptor map (one network pass)."""
        dense, heat, reliability, h, w = self._dense(gray)
        return self._detect(dense, heat, reliability, h, w, gray.shape), DescriptorMap(dense, h, w, *gray.shape)

    def _detect(self, dense: torch.Tensor, heat: torch.Tensor, reliability: torch.Tensor, h: int, w: int,
                shape: tuple[int, int]) -> XFeatures:
        peaks = (heat == F.max_pool2d(heat, 5, stride=1, padding=2)) & (heat > self.threshold)
        yx = peaks[0, 0].nonzero()
        if len(yx) == 0:
            return XFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 64), np.float32), np.zeros(0, np.float32))
        xy = yx.flip(-1).to(torch.float32)
        scores = heat[0, 0, yx[:, 0], yx[:, 1]] * _sample(reliability, xy, h, w, "bilinear")[:, 0]
        keep = torch.argsort(-scores)[: self.top_k]
        xy, scores = xy[keep], scores[keep]
        descriptors = F.normalize(_sample(dense, xy, h, w, "bicubic"), dim=-1)
        scale = torch.tensor([shape[1] / w, shape[0] / h])
        keypoints = (xy + 0.5) * scale  # pixel index -> project convention, in the original image
        return XFeatures(keypoints.cpu().numpy().astype(np.float32), descriptors.cpu().numpy().astype(np.float32),
                         scores.cpu().numpy().astype(np.float32))

    @torch.inference_mode()
    def describe(self, gray: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
        """Unit descriptors [N, 64] of the image at given pixels [N, 2] (project convention), e.g. tracked
        corners that carry map points."""
        return self.dense_map(gray).describe(keypoints)

    @torch.inference_mode()
    def dense_map(self, gray: np.ndarray) -> DescriptorMap:
        """The image's dense descriptor map, to describe any pixels of it later without the network."""
        dense, _, _, h, w = self._dense(gray)
        return DescriptorMap(dense, h, w, gray.shape[0], gray.shape[1])


@dataclass
class DescriptorMap:
    """XFeat's descriptor map [1, 64, h/8, w/8] of an image of `height` x `width` run at h x w."""

    dense: torch.Tensor
    h: int
    w: int
    height: int
    width: int

    @torch.inference_mode()
    def describe(self, keypoints: np.ndarray) -> np.ndarray:
        """Unit descriptors [N, 64] at pixels [N, 2] of the image (project convention)."""
        if len(keypoints) == 0:
            return np.zeros((0, 64), np.float32)
        scale = torch.tensor([self.w / self.width, self.h / self.height])
        xy = torch.from_numpy(np.asarray(keypoints, np.float32)) * scale - 0.5
        return F.normalize(_sample(self.dense, xy, self.h, self.w, "bicubic"), dim=-1).cpu().numpy().astype(
            np.float32)


def mutual_matches(a: np.ndarray, b: np.ndarray, min_cossim: float = 0.82) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of descriptor pairs (unit rows of a [N, 64], b [M, 64]) that are each other's nearest
    neighbour with a cosine similarity above `min_cossim` (XFeat's matcher)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    similarity = a @ b.T
    best_b = similarity.argmax(axis=1)
    best_a = similarity.argmax(axis=0)
    rows = np.arange(len(a))
    ia = np.flatnonzero((best_a[best_b] == rows) & (similarity[rows, best_b] > min_cossim))
    return ia.astype(np.int64), best_b[ia].astype(np.int64)
