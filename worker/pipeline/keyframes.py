"""Keyframe selection from poses: the first frame, then every N frames or when the camera moved or turned enough
since the last keyframe (used where the pose source leaves the choice to the engine: given poses, RGB-D odometry).

"Enough" is measured against the scene, so that it does not depend on the pose units or on the scene's size (a car
moves 0.8 m a frame, a hand-held camera over a desk 3 mm): the last keyframe's view is a grid of its pixels at their
depth (the keyframe's sensor depth or its source's, else a plane at the median depth multi-view stereo found for a
recent keyframe); a keyframe is due when the median parallax of those points (the angle between the rays from the
two camera centres, about the motion over the depth, less for motion along the view) passes a limit, when less
than a share of them is left inside the frame, or when the camera came closer to them by a share of their depth
(driving forward moves the view along its axis: little parallax, but what the last keyframe saw from afar is now
seen magnified, finer than its surfels; a car at 0.8 m a frame with the scene 12 m ahead needs a keyframe every 2
frames, not every 5). Until any depth is known (posed RGB's first frames, before multi-view stereo has estimated a
keyframe), only turns and the every-N floor make keyframes: a distance in pose units would make every frame a
keyframe in a scene measured in large units and none in small ones (ICL's poses x10: its first 18 frames were all
keyframes). A selector without a parallax rule (`depth_ratio` None) judges `translation`.

A blurred frame makes a poor keyframe (its colours smear into the map and its depth is worse): when a keyframe is
due and the frame is markedly blurrier than the recent frames (sharpness below `blur_ratio` times their median),
the keyframe waits for the next frame, at most `blur_delay` frames. Sharpness is the variance of the Laplacian of
the grey image at low resolution (`sharpness`, a fraction of a millisecond per 320x240 frame).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from worker.config import FrontendConfig
from worker.data.sharpness import sharpness
from worker.geometry import Intrinsics, relative_transform, sim3_decompose, so3_log
from worker.geometry.scene_units import median_depth

SHARPNESS_HISTORY = 8  # recent frames whose median sharpness a frame is compared with
MIN_HISTORY = 3  # frames needed before a frame can be judged blurred
VIEW_GRID = (16, 12)  # the pixels (columns, rows) a keyframe's view is judged by
MIN_VIEW_POINTS = 20  # valid depths needed to judge the view by the keyframe's own depth

__all__ = ["KeyframeView", "MotionKeyframeSelector", "median_depth"]


class MotionKeyframeSelector:
    """Decides, frame by frame, whether a pose starts a new keyframe (see the module docstring)."""

    def __init__(self, every: int, translation: float, rotation_deg: float, blur_ratio: float = 0.0,
                 blur_delay: int = 2, depth_ratio: float | None = None, min_overlap: float = 0.0,
                 approach: float = 0.0) -> None:
        """`every`: a keyframe at least every N frames; `translation` (pose units): the motion that makes a keyframe
        when there is no parallax rule; `depth_ratio`: the parallax (radians, about the motion over the depth) of the
        last keyframe's view that makes one once a scene depth is known (None: always `translation`); `min_overlap`:
        a keyframe once less than this fraction of that view is in the frame (0: not judged); `approach`: a keyframe
        once the median depth of that view's points in the frame has shrunk by this fraction (0: not judged).
        `blur_ratio` 0 never delays a keyframe for blur."""
        self.every = every
        self.translation = translation
        self.rotation = math.radians(rotation_deg)
        self.depth_ratio = depth_ratio
        self.min_overlap = min_overlap
        self.approach = approach
        self.blur_ratio = blur_ratio
        self.blur_delay = blur_delay
        self.last_pose: np.ndarray | None = None
        self.view: KeyframeView | None = None  # what the last keyframe saw, once a depth of it is known
        self.scene_depth: float | None = None  # the newest median scene depth known (pose units)
        self.frames_since = 0
        self.delayed = 0  # frames the due keyframe has waited for a sharper one
        self.recent_sharpness: deque[float] = deque(maxlen=SHARPNESS_HISTORY)
        self._sharpness: float | None = None  # the current frame's, from `observe`

    @classmethod
    def from_config(cls, fc: FrontendConfig) -> MotionKeyframeSelector:
        """The selector with the session's frontend settings."""
        return cls(fc.keyframe_every, fc.keyframe_translation, fc.keyframe_rotation_deg, fc.keyframe_blur_ratio,
                   fc.keyframe_blur_delay, depth_ratio=fc.keyframe_parallax, min_overlap=fc.keyframe_min_overlap,
                   approach=fc.keyframe_approach)

    def observe(self, image: np.ndarray) -> None:
        """Score the current frame's sharpness (before `is_keyframe` for that frame); without it, blur is not
        judged."""
        if self.blur_ratio > 0:
            self._sharpness = sharpness(image)

    def set_scene_depth(self, median_depth: float | None) -> None:
        """A median scene depth (pose units) learnt after the last keyframe was made, e.g. from the multi-view
        depth of a recent keyframe: it measures the motion from the last keyframe until that keyframe's own depth
        is known."""
        if median_depth is not None and math.isfinite(median_depth) and median_depth > 0:
            self.scene_depth = float(median_depth)

    def is_keyframe(self, pose: np.ndarray, force: bool = False, depth: np.ndarray | None = None,
                    camera: Intrinsics | None = None) -> bool:
        """Whether `pose` (c2w 4x4) is a keyframe (always when `force`); updates the selector's state. `depth`
        (z-depth [H, W] of this frame, 0 = unknown) and `camera` (at the depth's size) describe the view a new
        keyframe keeps for the next decisions."""
        self.frames_since += 1
        score, self._sharpness = self._sharpness, None
        blurred = self._blurred(score)
        if score is not None:
            self.recent_sharpness.append(score)
        due = force or self.last_pose is None or self.frames_since >= self.every or self._moved(pose, camera)
        if not due:
            return False
        if blurred and not force and self.last_pose is not None and self.delayed < self.blur_delay:
            self.delayed += 1
            return False
        self.last_pose = np.asarray(pose, np.float64).copy()
        self.view = KeyframeView.of(depth, camera)
        self.set_scene_depth(median_depth(depth))
        self.frames_since = 0
        self.delayed = 0
        return True

    def _blurred(self, score: float | None) -> bool:
        """Whether the frame is markedly blurrier than the median of the recent frames."""
        if score is None or len(self.recent_sharpness) < MIN_HISTORY:
            return False
        return score < self.blur_ratio * float(np.median(self.recent_sharpness))

    def _moved(self, pose: np.ndarray, camera: Intrinsics | None) -> bool:
        """Whether the camera turned, or moved enough for the scene it sees: the parallax of the last keyframe's
        view (its depth, else a plane at the scene's median depth), the share of that view still in the frame;
        while no depth is known, nothing but the turn (module docstring)."""
        rel = relative_transform(torch.from_numpy(self.last_pose), torch.from_numpy(np.asarray(pose, np.float64)))
        _, R, t = sim3_decompose(rel)
        if float(so3_log(R).norm()) > self.rotation:
            return True
        if self.depth_ratio is None:
            return float(t.norm()) > self.translation
        if self.scene_depth is None:
            return False
        view = self.view or (None if camera is None else KeyframeView.plane(self.scene_depth, camera))
        if view is None:
            return float(t.norm()) > self.depth_ratio * self.scene_depth
        rel = rel.numpy()
        if view.parallax(rel[:3, 3]) > self.depth_ratio:
            return True
        if self.approach > 0 and view.approach(rel) > self.approach:
            return True
        return self.min_overlap > 0 and camera is not None and view.overlap(rel, camera) < self.min_overlap

    def state_dict(self) -> dict:
        return {"last_pose": self.last_pose, "frames_since": self.frames_since, "delayed": self.delayed,
                "recent_sharpness": list(self.recent_sharpness), "scene_depth": self.scene_depth,
                "view": None if self.view is None else self.view.points}

    def load_state_dict(self, d: dict) -> None:
        self.last_pose = None if d["last_pose"] is None else np.asarray(d["last_pose"], np.float64)
        self.frames_since = int(d["frames_since"])
        self.delayed = int(d.get("delayed", 0))
        self.recent_sharpness = deque((float(v) for v in d.get("recent_sharpness", [])), maxlen=SHARPNESS_HISTORY)
        self.scene_depth = None if d.get("scene_depth") is None else float(d["scene_depth"])
        points = d.get("view")
        self.view = None if points is None else KeyframeView(np.asarray(points, np.float64).reshape(-1, 3))


@dataclass
class KeyframeView:
    """A keyframe's view as a few points in its camera: a grid of its pixels at their depth."""

    points: np.ndarray  # [N, 3], keyframe camera

    @classmethod
    def of(cls, depth: np.ndarray | None, camera: Intrinsics | None) -> KeyframeView | None:
        """The view of a z-depth map seen by `camera` (at the map's size); None without enough valid depth."""
        if depth is None or camera is None:
            return None
        depth = np.asarray(depth, np.float64)
        h, w = depth.shape[:2]
        rows = ((np.arange(VIEW_GRID[1]) + 0.5) * h / VIEW_GRID[1]).astype(int)
        cols = ((np.arange(VIEW_GRID[0]) + 0.5) * w / VIEW_GRID[0]).astype(int)
        z = depth[np.ix_(rows, cols)]
        u, v = np.meshgrid(cols + 0.5, rows + 0.5)
        valid = np.isfinite(z) & (z > 0)
        if valid.sum() < MIN_VIEW_POINTS:
            return None
        sx, sy = w / camera.width, h / camera.height  # the depth may be at another size than the camera
        x = (u[valid] - camera.cx * sx) / (camera.fx * sx)
        y = (v[valid] - camera.cy * sy) / (camera.fy * sy)
        return cls(np.stack([x * z[valid], y * z[valid], z[valid]], axis=1))

    @classmethod
    def plane(cls, depth: float | None, camera: Intrinsics) -> KeyframeView | None:
        """The view of a fronto-parallel plane at `depth` (a scene known only by its median depth)."""
        if depth is None:
            return None
        return cls.of(np.full((VIEW_GRID[1], VIEW_GRID[0]), depth), camera)

    def parallax(self, centre: np.ndarray) -> float:
        """The median angle (radians) between the rays to the points from the keyframe's camera centre and from
        `centre` (another camera's, in the keyframe's frame): about the motion over the depth sideways to the
        view, less for motion along it."""
        a = self.points / np.linalg.norm(self.points, axis=1, keepdims=True)
        b = self.points - np.asarray(centre, np.float64)
        b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
        return float(np.median(np.arccos(np.clip((a * b).sum(axis=1), -1.0, 1.0))))

    def approach(self, relative: np.ndarray) -> float:
        """How much closer a camera at `relative` (its c2w pose in the keyframe's camera frame) is to the points
        than the keyframe: 1 - the median ratio of their depths in that camera to their depths in the keyframe,
        over the points in front of it (0 when none is, negative when it moved away)."""
        w2c = np.linalg.inv(relative)
        z = self.points @ w2c[2, :3] + w2c[2, 3]
        ahead = z > 1e-9
        if not ahead.any():
            return 0.0
        return float(1.0 - np.median(z[ahead] / self.points[ahead, 2]))

    def overlap(self, relative: np.ndarray, camera: Intrinsics) -> float:
        """The fraction of the points a camera at `relative` (its c2w pose in the keyframe's camera frame) sees
        inside its image."""
        w2c = np.linalg.inv(relative)
        p = self.points @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        ahead = z > 1e-9
        u = camera.fx * p[:, 0] / np.where(ahead, z, 1.0) + camera.cx
        v = camera.fy * p[:, 1] / np.where(ahead, z, 1.0) + camera.cy
        inside = ahead & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        return float(inside.mean())
