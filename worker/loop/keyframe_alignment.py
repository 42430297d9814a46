"""Dense edges between RGB-D keyframes that see the same surfaces: each new keyframe is aligned, photometrically and
geometrically, to the older keyframes its pose puts nearest (DVO-SLAM's keyframe graph). The edges tie a keyframe to
every stretch of the session that saw its view, not only to the previous keyframe, so drift is corrected wherever the
camera comes back near a place, long before appearance-based loop detection would fire.

The alignment is RGB-D odometry's (worker.tracking.dense_alignment: coarse-to-fine Gauss-Newton on intensity and
point-to-plane residuals); an edge is kept only when the two keyframes overlap well and their depth fits closely after
it. Keyframes are held as grey uint8 and float16 depth at a working size of at most `WORKING_SIDE` pixels.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from worker.tracking.dense_alignment import (
    AlignmentResult,
    AlignmentSettings,
    PyramidLevel,
    align,
    build_pyramid,
    kernels,
)
from worker.tracking.motion import relative_motion

WORKING_SIDE = 320  # keyframes are aligned with their long side halved down to at most this many pixels
PYRAMID_LEVELS = 3
CACHED_PYRAMIDS = 16  # pyramids of recently aligned keyframes kept (a keyframe is often a neighbour several times)
EDGE_RATIO = 0.05  # depth downsampling: neighbours this much deeper (relative) are a different surface


@dataclass(frozen=True)
class AlignmentEdge:
    """The pose of keyframe `j` in keyframe `i` (T_i^-1 T_j) measured by dense alignment, with its overlap."""

    i: int
    j: int
    relative: np.ndarray
    overlap: float


@dataclass
class _Keyframe:
    grey: np.ndarray  # uint8 [H, W]
    depth: np.ndarray  # float16 [H, W], 0 = none
    K: np.ndarray  # float64 3x3 at this size
    scale: float  # this size over the size the keyframe came at


def _working_size(grey: np.ndarray, depth: np.ndarray, K: np.ndarray) -> _Keyframe:
    """The keyframe halved until its long side is at most WORKING_SIDE (area for intensity, edge-aware for depth)."""
    depth, scale = np.ascontiguousarray(depth, np.float32), 1.0
    while max(grey.shape) > WORKING_SIDE:
        grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
        depth = kernels().downsample_depth(depth, EDGE_RATIO)
        scale *= 0.5
    return _Keyframe(np.ascontiguousarray(grey, np.uint8), depth.astype(np.float16), _scaled(K, scale), scale)


def _scaled(K: np.ndarray, scale: float) -> np.ndarray:
    out = np.array(K, np.float64)
    out[:2] *= scale
    return out


class KeyframeAlignment:
    """Keyframes with their intensity and depth, and the dense edges of a new one to its nearest older ones."""

    def __init__(self, neighbours: int = 4, max_distance: float = 0.3, max_rotation_deg: float = 20.0,
                 min_overlap: float = 0.5, max_residual: float = 0.01, max_photometric: float = 0.12) -> None:
        self.neighbours = neighbours  # older keyframes aligned to per new keyframe, nearest first
        self.max_distance = max_distance  # ... at most this far (scene length units) ...
        self.max_rotation_deg = max_rotation_deg  # ... and turned at most this much from it
        self.min_overlap = min_overlap  # an edge needs this share of the older keyframe's surface found again
        self.max_residual = max_residual  # ... and a robust depth residual at most this (scene length units)
        self.max_photometric = max_photometric  # ... and a robust intensity residual at most this (0..1 scale)
        self.settings = AlignmentSettings()
        self.keyframes: dict[int, _Keyframe] = {}
        self._pyramids: OrderedDict[int, list[PyramidLevel]] = OrderedDict()
        self.tried = self.kept = 0

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self.keyframes

    def __len__(self) -> int:
        return len(self.keyframes)

    def add(self, kf_id: int, grey: np.ndarray, depth: np.ndarray, K: np.ndarray) -> None:
        """Keep keyframe `kf_id`: grey uint8 [H, W], its depth [H, W] (pose units, 0 = none) and camera matrix."""
        self.keyframes[int(kf_id)] = _working_size(grey, depth, K)

    def reproject(self, K: np.ndarray) -> None:
        """Every keyframe's camera from now on is `K` (at the size keyframes come at): the session's camera was
        re-estimated."""
        for keyframe in self.keyframes.values():
            keyframe.K = _scaled(K, keyframe.scale)
        self._pyramids.clear()

    def edges(self, kf_id: int, poses: dict[int, np.ndarray], unit: float, skip: set[int] | frozenset = frozenset()
              ) -> list[AlignmentEdge]:
        """Dense edges from the older keyframes nearest to `kf_id` (by `poses`, camera-to-world, in pose units of
        which `unit` make one scene length unit) to it, leaving out the keyframes in `skip`."""
        j = int(kf_id)
        if j not in self.keyframes or j not in poses:
            return []
        candidates = []
        for i, pose in poses.items():
            if i >= j or i in skip or i not in self.keyframes:
                continue
            moved, turn = relative_motion(pose, poses[j])
            if moved / unit <= self.max_distance and turn <= self.max_rotation_deg:
                candidates.append((moved / unit + np.radians(turn), i, np.linalg.inv(pose) @ poses[j]))
        candidates.sort(key=lambda c: c[0])
        out = []
        for _, i, relative in candidates[: self.neighbours]:
            self.tried += 1
            fit = align(self._pyramid(i), self._pyramid(j), np.linalg.inv(relative), self.settings)
            if self._fits(fit, unit):
                out.append(AlignmentEdge(i, j, np.linalg.inv(fit.T), fit.overlap))
        self.kept += len(out)
        return out

    def _fits(self, fit: AlignmentResult, unit: float) -> bool:
        """Whether an alignment settled where both images agree: a wrong minimum (a flat desk slid along itself) can
        fit the depth well while the intensities do not."""
        return (fit.ok and bool(np.all(np.isfinite(fit.T))) and fit.overlap >= self.min_overlap
                and fit.geometric_rms <= self.max_residual * unit and fit.photometric_rms <= self.max_photometric)

    def _pyramid(self, kf_id: int) -> list[PyramidLevel]:
        pyramid = self._pyramids.get(kf_id)
        if pyramid is None:
            keyframe = self.keyframes[kf_id]
            pyramid = build_pyramid(keyframe.grey.astype(np.float32) / 255.0, keyframe.depth.astype(np.float32),
                                    keyframe.K, PYRAMID_LEVELS, edge_ratio=EDGE_RATIO)
            self._pyramids[kf_id] = pyramid
            while len(self._pyramids) > CACHED_PYRAMIDS:
                self._pyramids.popitem(last=False)
        self._pyramids.move_to_end(kf_id)
        return pyramid

    def state_dict(self) -> dict[str, Any]:
        keys = list(self.keyframes)
        return {"keys": keys, "greys": [self.keyframes[k].grey for k in keys],
                "depths": [self.keyframes[k].depth for k in keys], "cameras": [self.keyframes[k].K for k in keys],
                "scales": [self.keyframes[k].scale for k in keys], "tried": self.tried, "kept": self.kept}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.keyframes = {int(k): _Keyframe(np.asarray(g, np.uint8), np.asarray(d, np.float16),
                                            np.asarray(K, np.float64), float(scale))
                          for k, g, d, K, scale in zip(state["keys"], state["greys"], state["depths"],
                                                       state["cameras"], state["scales"])}
        self._pyramids.clear()
        self.tried, self.kept = int(state.get("tried", 0)), int(state.get("kept", 0))
