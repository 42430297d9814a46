"""Incremental tracking with submaps (paper 4.1): chain per-submap predictions into one Sim(3) world trajectory.

The stream is cut into submaps of `submap_length` frames that share one frame: the last frame of submap a is the
first frame of submap b. The hidden state is re-initialised for every submap, so each submap has its own frame
(its first camera) and its own scale. The overlap frame is predicted twice, once at the end of submap a and once
as the first frame of submap b; both camera-frame point maps show the same image, so they differ only by a scale
that a confidence-weighted robust least squares fit recovers (the eq. 12 form). With that scale the origin of
submap b is placed in the world and every frame of b gets a Sim(3) camera-to-world pose whose scale converts its
camera-frame units (those of submap b) into world units.

Keyframes: the first frame of every submap (it carries the inter-submap link and the submap's reference), plus any
frame whose motion since the last keyframe is large relative to the scene: translation above
`keyframe_translation` times the last keyframe's median depth, or rotation above `keyframe_rotation_deg`. Ratios
to depth make the test independent of the submap's arbitrary scale; a translation of ~10% of the scene depth or a
rotation of ~10 degrees changes about that fraction of the view, which is where new surfels start to matter.

The tracked overlap frame is reported once, as the first frame of the new submap (its keyframe node and surfels
use that submap's units), so every keyframe belongs to exactly one submap.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from protocol.codec import pack, unpack
from worker.geometry import Intrinsics, relative_transform, so3_log, umeyama
from worker.loop.pose_graph import PoseGraphEdge

from .types import HiddenState, StepOutput

logger = logging.getLogger(__name__)


class RecurrentModel(Protocol):
    def init_state(self, batch: int = 1) -> HiddenState: ...

    def step(self, image: torch.Tensor, state: HiddenState, update: bool = True) -> StepOutput: ...


POSE_SOURCES = ("head", "pointmap")


@dataclass(frozen=True)
class TrackerConfig:
    """Submap length (frames, overlap included), keyframe thresholds (see the module docstring) and where a frame's
    pose in its submap comes from: the model's pose head, or the rigid fit of its camera-frame point map onto its
    world-frame (submap-frame) point map (`pointmap_pose`)."""

    submap_length: int = 8
    keyframe_translation: float = 0.10
    keyframe_rotation_deg: float = 10.0
    min_scale_points: int = 32
    pose_source: str = "head"

    def __post_init__(self) -> None:
        if self.submap_length < 2:
            raise ValueError(f"submap_length must be at least 2 (one frame overlaps), got {self.submap_length}")
        if self.pose_source not in POSE_SOURCES:
            raise ValueError(f"pose_source must be one of {POSE_SOURCES}, got {self.pose_source!r}")


@dataclass
class CameraSurfels:
    """Per-pixel surfel attributes of one frame in its camera frame, at model resolution H x W."""

    points: torch.Tensor  # [H,W,3]
    conf: torch.Tensor  # [H,W]
    opacity: torch.Tensor  # [H,W]
    quats: torch.Tensor  # [H,W,4] wxyz
    scales: torch.Tensor  # [H,W,2]
    colors: torch.Tensor  # [H,W,3]

    @classmethod
    def from_step(cls, out: StepOutput, b: int = 0) -> CameraSurfels:
        return cls(out.points_cam[b], out.conf[b], out.opacity[b], out.quats[b], out.scales[b], out.colors[b])


@dataclass
class TrackedFrame:
    """One tracked frame: world pose (Sim(3) c2w), pose in its submap's frame (SE(3)), camera-frame surfels."""

    index: int
    pose_world: torch.Tensor  # [4,4] float64
    pose_submap: torch.Tensor  # [4,4] float64
    surfels: CameraSurfels
    intrinsics: Intrinsics | None
    submap_id: int
    is_keyframe: bool
    keyframe_id: int  # the keyframe this frame follows (itself when it is one)


@dataclass
class KeyframeRecord:
    """What loop closure needs of a keyframe: its submap, poses, and camera-frame points P (fp16, model res.)."""

    index: int
    submap_id: int
    pose_submap: torch.Tensor
    pose_world: torch.Tensor
    points: torch.Tensor
    conf: torch.Tensor

    def to_dict(self) -> dict:
        return {"index": self.index, "submap_id": self.submap_id, "pose_submap": self.pose_submap,
                "pose_world": self.pose_world, "points": self.points, "conf": self.conf}

    @classmethod
    def from_dict(cls, d: Mapping) -> KeyframeRecord:
        t = torch.from_numpy
        return cls(int(d["index"]), int(d["submap_id"]), t(np.asarray(d["pose_submap"])),
                   t(np.asarray(d["pose_world"])), t(np.asarray(d["points"])), t(np.asarray(d["conf"])))


@dataclass
class FinishedSubmap:
    """A closed submap: its final hidden state M_a and the keyframes it covers (for the bag of hidden states)."""

    submap_id: int
    state: HiddenState
    keyframe_ids: list[int]
    frame_ids: list[int]


def relative_scale(target: torch.Tensor, source: torch.Tensor, weights: torch.Tensor | None = None,
                   iterations: int = 5, huber: float = 0.05, min_points: int = 32, max_points: int = 20000) -> float:
    """s minimising sum_k w_k rho(|target_k - s source_k| / |target_k|) (eq. 12, confidence-weighted, Huber IRLS).

    target, source: [..., 3] camera-frame points of the same pixels; weights [...] (e.g. confidences). Residuals
    are relative to the target's range so near and far points count alike. At most `max_points` pixels (a regular
    subsample) enter the fit. Raises ValueError when fewer than `min_points` valid pairs exist.
    """
    a = target.reshape(-1, 3)
    step = max(1, a.shape[0] // max_points)
    a = a[::step].double()
    b = source.reshape(-1, 3)[::step].double()
    w = torch.ones(a.shape[0], dtype=torch.float64) if weights is None else weights.reshape(-1)[::step].double()
    valid = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1) & torch.isfinite(w) & (w > 0)
    valid &= (a[:, 2] > 1e-6) & (b[:, 2] > 1e-6)
    if int(valid.sum()) < min_points:
        raise ValueError(f"relative scale needs at least {min_points} valid point pairs, got {int(valid.sum())}")
    a, b, w = a[valid], b[valid], w[valid]
    inv_range2 = 1.0 / (a * a).sum(-1)
    robust = torch.ones_like(w)
    s = 1.0
    for _ in range(iterations):
        ww = w * robust * inv_range2
        s = float((ww * (a * b).sum(-1)).sum() / (ww * (b * b).sum(-1)).sum().clamp_min(1e-300))
        r = (a - s * b).norm(dim=-1) * inv_range2.sqrt()
        robust = torch.where(r <= huber, torch.ones_like(r), huber / r.clamp_min(1e-12))
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"relative scale fit failed (s={s})")
    return s


def pointmap_pose(points_cam: torch.Tensor, points_world: torch.Tensor, weights: torch.Tensor,
                  max_points: int = 4096) -> torch.Tensor:
    """Camera-to-world SE(3) [4,4] float64 that maps a frame's camera-frame points onto its world-frame points.

    The two point maps show the same pixels, so the rigid transform between them is the camera pose the world map
    encodes: a weighted Umeyama fit without scale (weights e.g. sqrt(conf * conf_world)) on a regular subsample
    of at most `max_points` pixels. Raises ValueError with fewer than 3 valid pixels.
    """
    a = points_cam.reshape(-1, 3)
    step = max(1, a.shape[0] // max_points)
    a = a[::step].double()
    b = points_world.reshape(-1, 3)[::step].double()
    w = weights.reshape(-1)[::step].double()
    valid = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1) & torch.isfinite(w) & (w > 0)
    if int(valid.sum()) < 3:
        raise ValueError(f"point-map pose needs at least 3 valid pixels, got {int(valid.sum())}")
    _, R, t = umeyama(a[valid], b[valid], with_scale=False, weights=w[valid])
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3], pose[:3, 3] = R, t
    return pose


def _scale_matrix(s: float) -> torch.Tensor:
    return torch.diag(torch.tensor([s, s, s, 1.0], dtype=torch.float64))


def _median_depth(points: torch.Tensor) -> float:
    z = points[::4, ::4, 2].reshape(-1).float()
    z = z[torch.isfinite(z) & (z > 0)]
    return float(z.median()) if z.numel() else 1.0


class SubmapTracker:
    """Feeds frames through the recurrent model in submaps and chains them into one Sim(3) trajectory."""

    def __init__(self, model: RecurrentModel, config: TrackerConfig | None = None) -> None:
        self.model = model
        self.config = config or TrackerConfig()
        self.submap_id = -1
        self.state: HiddenState | None = None
        self.frames_in_submap = 0
        self.submap_to_world = torch.eye(4, dtype=torch.float64)  # G_b: submap frame -> world (Sim(3))
        self.submap_frames: list[int] = []
        self.submap_keyframes: list[int] = []
        self.keyframes: dict[int, KeyframeRecord] = {}
        self.constraints: list[PoseGraphEdge] = []  # sequential and inter-submap keyframe edges
        self.submap_links: list[tuple[int, int, torch.Tensor]] = []  # (a, b, G_a^-1 G_b)
        self.overlap_scales: list[float] = []
        self.scale_failures = 0
        self.estimated_intrinsics: Intrinsics | None = None
        self.finished: list[FinishedSubmap] = []
        self.last_keyframe: int | None = None
        self.frames_tracked = 0

    # ---- public API -------------------------------------------------------------------------------------------

    @torch.no_grad()
    def track(self, index: int, image: torch.Tensor, intrinsics: Intrinsics | None = None) -> TrackedFrame:
        """Track one frame (image [1,3,H,W] in [0,1] at model resolution; intrinsics at that resolution).

        Without intrinsics (uncalibrated input) the frame reports ones estimated from the first frame of its
        submap's point map (focal by a robust fit, principal point at the centre), or None if that fit fails.
        """
        if image.ndim != 4 or image.shape[0] != 1 or image.shape[1] != 3:
            raise ValueError(f"track expects one image [1,3,H,W], got {tuple(image.shape)}")
        if self.state is None:
            return self._start_submap(index, image, intrinsics, previous=None)
        out = self.model.step(image, self.state, update=True)
        self.state = out.state
        self.frames_in_submap += 1
        pose_submap = self._submap_pose(out)
        if self.frames_in_submap == self.config.submap_length:
            return self._start_submap(index, image, intrinsics, previous=(out, pose_submap))
        return self._emit(index, out, pose_submap, intrinsics, force_keyframe=False)

    def pop_finished_submaps(self) -> list[FinishedSubmap]:
        """Submaps closed since the last call, with their final hidden states (hand these to the bag)."""
        done, self.finished = self.finished, []
        return done

    def keyframe_points(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """P_j^b: keyframe `index`'s camera-frame points [H,W,3] and confidence [H,W] from incremental tracking."""
        if index not in self.keyframes:
            raise ValueError(f"frame {index} is not a keyframe")
        rec = self.keyframes[index]
        return rec.points.float(), rec.conf.float()

    def keyframe_poses(self) -> dict[int, torch.Tensor]:
        return {k: r.pose_world for k, r in self.keyframes.items()}

    def sequential_constraints(self) -> list[PoseGraphEdge]:
        return [e for e in self.constraints if e.kind == "sequential"]

    def inter_submap_constraints(self) -> list[PoseGraphEdge]:
        return [e for e in self.constraints if e.kind == "inter_submap"]

    # ---- internals --------------------------------------------------------------------------------------------

    def _start_submap(self, index: int, image: torch.Tensor, intrinsics: Intrinsics | None,
                      previous: tuple[StepOutput, torch.Tensor] | None) -> TrackedFrame:
        """Open a new submap at this frame; with `previous` (the frame as the last of the old submap), link them."""
        if previous is not None:
            self.finished.append(FinishedSubmap(self.submap_id, self.state, list(self.submap_keyframes),
                                                list(self.submap_frames)))
        self.submap_id += 1
        self.state = self.model.init_state(batch=1)
        out = self.model.step(image, self.state, update=True)
        self.state = out.state
        self.frames_in_submap = 1
        self.submap_frames, self.submap_keyframes = [], []
        self.estimated_intrinsics = self._estimate_intrinsics(out)
        pose_submap = self._submap_pose(out)
        if previous is not None:
            prev_out, prev_pose = previous
            try:
                s = relative_scale(prev_out.points_cam[0], out.points_cam[0],
                                   (prev_out.conf[0] * out.conf[0]).sqrt(), min_points=self.config.min_scale_points)
            except ValueError as err:  # degenerate predictions: keep the scale and say so, rather than stop
                logger.warning("submap %d: overlap scale fit failed (%s); using 1.0", self.submap_id, err)
                s = 1.0
                self.scale_failures += 1
            self.overlap_scales.append(s)
            # camera of the overlap frame: world <- camera (old units) <- camera (new units) <- new submap frame
            new_to_world = self.submap_to_world @ prev_pose @ _scale_matrix(s) @ torch.linalg.inv(pose_submap)
            link = relative_transform(self.submap_to_world, new_to_world)
            self.submap_links.append((self.submap_id - 1, self.submap_id, link))
            self.submap_to_world = new_to_world
        return self._emit(index, out, pose_submap, intrinsics, force_keyframe=True)

    def _submap_pose(self, out: StepOutput) -> torch.Tensor:
        """The frame's SE(3) pose in its submap, from the configured source (pose head if the fit fails)."""
        if self.config.pose_source == "pointmap":
            try:
                return pointmap_pose(out.points_cam[0], out.points_world[0], (out.conf[0] * out.conf_world[0]).sqrt())
            except ValueError as err:
                logger.warning("point-map pose failed (%s); using the pose head", err)
        return out.pose_c2w[0].double()

    @staticmethod
    def _estimate_intrinsics(out: StepOutput) -> Intrinsics | None:
        from .focal import estimate_focal, intrinsics_from_focal

        H, W = out.points_cam.shape[1:3]
        try:
            return intrinsics_from_focal(estimate_focal(out.points_cam[0], out.conf[0]), W, H)
        except ValueError:
            return None

    def _is_keyframe(self, pose_world: torch.Tensor) -> bool:
        if self.last_keyframe is None:
            return True
        ref = self.keyframes[self.last_keyframe]
        rel = relative_transform(ref.pose_world, pose_world)  # in the keyframe's camera units
        s = float(torch.linalg.det(rel[:3, :3]).abs() ** (1 / 3))
        angle = float(so3_log(rel[:3, :3] / s).norm())
        distance = float(rel[:3, 3].norm())
        depth = _median_depth(ref.points)
        return (distance > self.config.keyframe_translation * depth
                or math.degrees(angle) > self.config.keyframe_rotation_deg)

    def _emit(self, index: int, out: StepOutput, pose_submap: torch.Tensor, intrinsics: Intrinsics | None,
              force_keyframe: bool) -> TrackedFrame:
        pose_world = self.submap_to_world @ pose_submap
        is_keyframe = force_keyframe or self._is_keyframe(pose_world)
        if is_keyframe:
            if self.last_keyframe is not None:
                prev = self.keyframes[self.last_keyframe]
                kind = "inter_submap" if force_keyframe else "sequential"
                self.constraints.append(PoseGraphEdge(self.last_keyframe, index,
                                                      relative_transform(prev.pose_world, pose_world).numpy(), kind))
            self.keyframes[index] = KeyframeRecord(index, self.submap_id, pose_submap, pose_world,
                                                   out.points_cam[0].detach().to(torch.float16),
                                                   out.conf[0].detach().to(torch.float16))
            self.last_keyframe = index
            self.submap_keyframes.append(index)
        self.submap_frames.append(index)
        self.frames_tracked += 1
        return TrackedFrame(index, pose_world, pose_submap, CameraSurfels.from_step(out),
                            intrinsics if intrinsics is not None else self.estimated_intrinsics, self.submap_id,
                            is_keyframe, index if is_keyframe else int(self.last_keyframe))

    # ---- snapshot ---------------------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """msgpack-able tracker state, enough to resume mid-submap (the model itself is not included)."""
        return {
            "config": {"submap_length": self.config.submap_length,
                       "keyframe_translation": self.config.keyframe_translation,
                       "keyframe_rotation_deg": self.config.keyframe_rotation_deg,
                       "min_scale_points": self.config.min_scale_points,
                       "pose_source": self.config.pose_source},
            "submap_id": self.submap_id,
            "state": None if self.state is None else self.state.to_bytes(torch.float32),
            "frames_in_submap": self.frames_in_submap,
            "submap_to_world": self.submap_to_world,
            "submap_frames": self.submap_frames,
            "submap_keyframes": self.submap_keyframes,
            "keyframes": [r.to_dict() for r in self.keyframes.values()],
            "constraints": [e.to_dict() for e in self.constraints],
            "submap_links": [{"a": a, "b": b, "link": link} for a, b, link in self.submap_links],
            "overlap_scales": self.overlap_scales,
            "scale_failures": self.scale_failures,
            "estimated_intrinsics": None if self.estimated_intrinsics is None else self.estimated_intrinsics.to_dict(),
            "finished": [{"submap_id": f.submap_id, "state": f.state.to_bytes(torch.float32),
                          "keyframe_ids": f.keyframe_ids, "frame_ids": f.frame_ids} for f in self.finished],
            "last_keyframe": self.last_keyframe,
            "frames_tracked": self.frames_tracked,
        }

    def load_state_dict(self, d: Mapping) -> None:
        self.config = TrackerConfig(**d["config"])
        self.submap_id = int(d["submap_id"])
        self.state = None if d["state"] is None else HiddenState.from_bytes(d["state"])
        self.frames_in_submap = int(d["frames_in_submap"])
        self.submap_to_world = torch.from_numpy(np.asarray(d["submap_to_world"]))
        self.submap_frames = [int(i) for i in d["submap_frames"]]
        self.submap_keyframes = [int(i) for i in d["submap_keyframes"]]
        self.keyframes = {int(r["index"]): KeyframeRecord.from_dict(r) for r in d["keyframes"]}
        self.constraints = [PoseGraphEdge.from_dict(e) for e in d["constraints"]]
        self.submap_links = [(int(x["a"]), int(x["b"]), torch.from_numpy(np.asarray(x["link"])))
                             for x in d["submap_links"]]
        self.overlap_scales = [float(s) for s in d["overlap_scales"]]
        self.scale_failures = int(d.get("scale_failures", 0))
        est = d.get("estimated_intrinsics")
        self.estimated_intrinsics = None if est is None else Intrinsics.from_dict(est)
        self.finished = [FinishedSubmap(int(f["submap_id"]), HiddenState.from_bytes(f["state"]),
                                        [int(i) for i in f["keyframe_ids"]], [int(i) for i in f["frame_ids"]])
                         for f in d["finished"]]
        self.last_keyframe = None if d["last_keyframe"] is None else int(d["last_keyframe"])
        self.frames_tracked = int(d["frames_tracked"])

    def to_bytes(self) -> bytes:
        return pack(self.state_dict())

    def load_bytes(self, data: bytes) -> None:
        self.load_state_dict(unpack(data))
