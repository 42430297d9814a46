"""Synthetic sequences: frames rendered on demand along a procedural scene's camera path (rooms,
worker.data.synthetic_scene; streets, worker.data.street), opened as `synthetic://seed=N?...` sources.

The scene names are re-exported here for the callers that know them by this module.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

from worker.data.frame import Frame
from worker.data.sources.base import DatasetError, FrameSource, SourceOptions
from worker.data.street import StreetScene
from worker.data.synthetic_scene import (  # noqa: F401 - re-exported
    HELD_OUT_SEED_START,
    Material,
    SceneLayout,
    SyntheticScene,
    default_intrinsics,
    generate_layout,
    is_held_out_seed,
    look_at_c2w,
)


class SyntheticSequence(FrameSource):
    """Frames rendered on demand along a scene's camera path, with exact depth, intrinsics and gt poses.

    Timestamps are index / fps. Options apply as for datasets; `resize` renders directly at that size.
    """

    def __init__(self, seed: int, num_frames: int = 60, width: int = 320, height: int = 240, revisit: bool = True,
                 fps: float = 30.0, options: SourceOptions | None = None, scene: str = "room") -> None:
        super().__init__(options or SourceOptions())
        if num_frames < 1 or width < 8 or height < 8 or fps <= 0:
            raise DatasetError(f"bad synthetic sequence: frames={num_frames}, size={width}x{height}, fps={fps}")
        if scene not in SCENE_KINDS:
            raise DatasetError(f"unknown synthetic scene {scene!r}; choose one of {SCENE_KINDS}")
        if scene == "street":
            self.scene = StreetScene(seed)
        else:
            self.scene = SyntheticScene(seed)
        self.name = f"synthetic-{seed}" if scene == "room" else f"synthetic-{scene}-{seed}"
        self.fps = float(fps)
        self.revisit = revisit
        size = self.options.resize or (width, height)
        native = self.options.intrinsics or default_intrinsics(width, height)
        self.intrinsics = native.scaled(*size)
        try:
            all_poses = self.scene.camera_path(num_frames, revisit)
        except ValueError as exc:
            raise DatasetError(str(exc)) from exc
        self._positions = list(self.options.selected(num_frames))
        self.poses = all_poses[self._positions]

    def __len__(self) -> int:
        return len(self._positions)

    def __iter__(self) -> Iterator[Frame]:
        for index, position in enumerate(self._positions):
            yield self.frame(index, position)

    def frame(self, index: int, position: int | None = None) -> Frame:
        """Render the index-th yielded frame."""
        position = self._positions[index] if position is None else position
        pose = self.poses[index]
        rgb, depth = self.scene.render(pose, self.intrinsics)
        return Frame(index=index, timestamp=position / self.fps, image=rgb, intrinsics=self.intrinsics,
                     depth=depth if self.options.use_gt_depth else None,
                     pose=pose.copy() if self.options.use_gt_poses else None, gt_pose=pose.copy())


def make_sequence(seed: int, num_frames: int = 60, width: int = 320, height: int = 240, revisit: bool = True,
                  **options) -> SyntheticSequence:
    """A synthetic sequence (a FrameSource). Extra keyword options: fps and the common SourceOptions."""
    fps = options.pop("fps", 30.0)
    return SyntheticSequence(seed, num_frames, width, height, revisit, fps, SourceOptions(**options))


SCENE_KINDS = ("room", "street")
_URI_KEYS = {"seed": int, "frames": int, "width": int, "height": int, "fps": float,
             "revisit": lambda v: v.lower() in ("1", "true", "yes"), "scene": str}


def parse_synthetic_uri(uri: str) -> dict:
    """Parameters of `synthetic://seed=3?frames=60&width=320&height=240[&revisit=1&fps=30&scene=street]`."""
    if not uri.startswith("synthetic://"):
        raise DatasetError(f"not a synthetic:// URI: {uri!r}")
    params = {}
    for part in filter(None, re.split(r"[?&/]", uri[len("synthetic://"):])):
        key, sep, value = part.partition("=")
        if not sep or key not in _URI_KEYS:
            raise DatasetError(f"bad synthetic URI part {part!r}; known keys: {', '.join(_URI_KEYS)}")
        try:
            params[key] = _URI_KEYS[key](value)
        except ValueError as exc:
            raise DatasetError(f"bad value for {key} in {uri!r}: {value!r}") from exc
    if "seed" not in params:
        raise DatasetError(f"synthetic URI needs a seed: {uri!r}")
    return params


def open_synthetic_uri(uri: str, options: SourceOptions, **extra) -> SyntheticSequence:
    """The SyntheticSequence a `synthetic://` URI describes (keyword `extra` overrides URI values)."""
    params = parse_synthetic_uri(uri) | extra
    try:
        return SyntheticSequence(params["seed"], params.get("frames", 60), params.get("width", 320),
                                 params.get("height", 240), params.get("revisit", True), params.get("fps", 30.0),
                                 options, params.get("scene", "room"))
    except ValueError as exc:
        raise DatasetError(str(exc)) from exc
