"""Loop closure as the engine runs it: detect candidates for each new keyframe, relocalize, keep the first verified
constraint (paper 4.2). Detection and relocalization are worker.loop's; this module wires them to the engine's
modes and makes their state snapshot-able.

Relocalization sources: "hidden_state" (f(I_j, M_a) with the bag of hidden states, monocular) and "pnp" (ORB + PnP
with keyframe i's 3D points: the tracker's predicted points or, in posed RGB-D mode, the given depth through
`DepthKeyframePoints`, which makes the constraint metric like the given poses), with XFeat matches where ORB's are
too few (`loop.xfeat_verification`: source "pnp_xfeat").
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from worker.config import LoopConfig
from worker.geometry import Intrinsics, unproject_depth
from worker.loop.descriptors import EncoderGeMDescriptor, OrbDescriptor, OrbFeatures
from worker.loop.detector import LoopDetector
from worker.loop.pnp import PnPRelocalizer
from worker.loop.relocalize import LoopConstraint
from worker.loop.vocabulary import SparseBag
from worker.loop.xfeat_matcher import XFeatKeyframeMatcher
from worker.pipeline.stage_times import StageTimes


class DepthKeyframePoints:
    """Keyframe depth in float16 and the camera it was taken with; offers the tracker's
    `keyframe_points(index) -> (points [H,W,3], conf [H,W])`, unprojected when asked, so that the PnP relocalizer
    can use them. A third of the memory of stored points, and snapshots reproduce the points exactly."""

    def __init__(self) -> None:
        self.depths: dict[int, torch.Tensor] = {}
        self.cameras: dict[int, torch.Tensor] = {}

    def __contains__(self, index: int) -> bool:
        return int(index) in self.depths

    def add(self, index: int, depth: torch.Tensor, K: torch.Tensor) -> None:
        self.depths[int(index)] = depth.detach().to(torch.float16).clone()
        self.cameras[int(index)] = K.detach().to(torch.float32).clone()

    def reproject(self, K: torch.Tensor) -> None:
        """Every keyframe's points from now on with camera K (the session's camera was re-estimated)."""
        for index in self.cameras:
            self.cameras[index] = K.detach().to(torch.float32).clone()

    def keyframe_points(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if index not in self.depths:
            raise ValueError(f"frame {index} is not a keyframe with depth")
        p = unproject_depth(self.depths[index].float(), self.cameras[index])
        return p, (p[..., 2] > 0).float() + 1.0

    def __len__(self) -> int:
        return len(self.depths)

    def state_dict(self) -> dict:
        keys = list(self.depths)
        return {"keys": keys, "depths": [self.depths[k].numpy() for k in keys],
                "cameras": [self.cameras[k].numpy() for k in keys]}

    def load_state_dict(self, d: dict) -> None:
        keys = [int(k) for k in d["keys"]]
        if "points" in d:  # snapshots before depth-only storage: the depth and the camera are in the points
            self.depths, self.cameras = {}, {}
            for k, points in zip(keys, d["points"]):
                points = torch.from_numpy(np.asarray(points)).float()
                self.add(k, points[..., 2], _camera_of_points(points))
            return
        self.depths = {k: torch.from_numpy(np.asarray(v, np.float16)) for k, v in zip(keys, d["depths"])}
        self.cameras = {k: torch.from_numpy(np.asarray(v, np.float32)) for k, v in zip(keys, d["cameras"])}


def _camera_of_points(points: torch.Tensor) -> torch.Tensor:
    """K of a camera-frame point map [H,W,3] (pixel centres at +0.5): least squares on u = fx x/z + cx."""
    H, W = points.shape[:2]
    z = points[..., 2]
    valid = z > 0
    if int(valid.sum()) < 2:
        raise ValueError("keyframe points hold too little depth to recover their camera")
    pixels = (torch.arange(W, dtype=torch.float64) + 0.5)[None, :].expand(H, W), \
        (torch.arange(H, dtype=torch.float64) + 0.5)[:, None].expand(H, W)
    K = torch.eye(3)
    for axis in (0, 1):
        ratio = (points[..., axis][valid] / z[valid]).double()
        A = torch.stack([ratio, torch.ones_like(ratio)], dim=-1)
        f, c = torch.linalg.lstsq(A, pixels[axis][valid][:, None]).solution.ravel().tolist()
        K[axis, axis], K[axis, 2] = f, c
    return K


def _entry_to_dict(entry: Any) -> dict:
    if isinstance(entry, OrbFeatures):
        d = {"kind": "orb", "keypoints": entry.keypoints, "descriptors": entry.descriptors,
             "width": entry.width, "height": entry.height}
        if entry.words is not None:  # kept so that a restore rebuilds the inverted index without quantizing
            d["words"] = entry.words.words.astype(np.uint16 if entry.words.words.max(initial=0) < 2**16
                                                  else np.int32)
            d["weights"] = entry.words.weights
        return d
    return {"kind": "vector", "value": entry.detach().cpu().numpy()}


def _entry_from_dict(d: dict) -> Any:
    if d["kind"] == "orb":
        words = None
        if "words" in d:
            words = SparseBag(np.asarray(d["words"]).astype(np.int32), np.asarray(d["weights"], np.float32))
        return OrbFeatures(np.asarray(d["keypoints"], np.float32), np.asarray(d["descriptors"], np.uint8),
                           int(d["width"]), int(d["height"]), words)
    return torch.from_numpy(np.asarray(d["value"]))


_SAME_AS_DETECTOR = {"kind": "detector"}  # a PnP entry that is the detector's own entry for the keyframe


class LoopCloser:
    """Per keyframe: query the detector, relocalize the candidates best first, return the first verified one."""

    def __init__(self, cfg: LoopConfig, model=None, tracker=None, bag=None, depth_points: DepthKeyframePoints | None
                 = None, timings: StageTimes | None = None) -> None:
        self.cfg = cfg
        self.timings = timings or StageTimes()
        orb = OrbDescriptor()
        if cfg.descriptor == "encoder":
            if model is None:
                raise ValueError("the encoder loop descriptor needs the model")
            descriptor = EncoderGeMDescriptor(model)
        else:
            descriptor = orb
        self.detector = LoopDetector(descriptor, exclusion_window=cfg.exclusion_frames, top_k=cfg.top_k,
                                     min_score=cfg.min_score, shortlist=cfg.shortlist,
                                     recent=min(cfg.recent_candidates, cfg.shortlist))
        self.pnp: PnPRelocalizer | None = None
        pnp_settings = {"min_inliers": cfg.min_inliers, "xfeat_min_inliers": cfg.xfeat_min_inliers,
                        "xfeat_per_keyframe": cfg.xfeat_per_keyframe}
        if depth_points is not None or cfg.relocalization == "pnp":
            xfeat = XFeatKeyframeMatcher() if cfg.xfeat_verification and cfg.xfeat_per_keyframe > 0 else None
            self.relocalizer = self.pnp = PnPRelocalizer(depth_points if depth_points is not None else tracker, orb,
                                                         xfeat=xfeat, **pnp_settings)
        else:
            from worker.loop.relocalize import HiddenStateRelocalizer

            self.relocalizer = HiddenStateRelocalizer(model, bag, tracker)
        self.last_loop_keyframe_count = -10**9
        self.keyframes_seen = 0
        self.rejected = 0

    def process_keyframe(self, index: int, image: torch.Tensor, intrinsics: Intrinsics | None
                         ) -> list[LoopConstraint]:
        """Register keyframe `index` (image [1,3,H,W] in [0,1]); its verified loop constraints (i, index), best
        candidate first, at most `max_loops_per_keyframe` of them (empty during the cooldown)."""
        with self.timings.measure("loop_detection"):
            candidates = self.detector.detect(index, image)
        descriptor = self.detector.descriptor_of(index)
        if self.pnp is not None:
            self.pnp.add_keyframe(index, image, descriptor if isinstance(descriptor, OrbFeatures) else None)
        self.keyframes_seen += 1
        if self.keyframes_seen - self.last_loop_keyframe_count <= self.cfg.loop_cooldown_keyframes:
            return []
        accepted: list[LoopConstraint] = []
        for candidate in candidates:
            try:
                with self.timings.measure("loop_relocalization"):
                    constraint = self.relocalizer.relocalize(candidate.match, index, image, intrinsics)
            except ValueError:  # e.g. the candidate's submap is still open: no cached state yet
                continue
            if not constraint.accepted:
                self.rejected += 1
                continue
            accepted.append(constraint)
            if len(accepted) >= self.cfg.max_loops_per_keyframe:
                break
        if accepted:
            self.last_loop_keyframe_count = self.keyframes_seen
        return accepted

    def state_dict(self) -> dict:
        """The keyframe database (descriptors with their bags of words; the PnP features that are the detector's
        own entries only by reference) and the counters."""
        detector = self.detector
        pnp_features = []
        for key, features in ({} if self.pnp is None else self.pnp.features).items():
            shared = key in detector and detector.descriptor_of(key) is features
            pnp_features.append(_SAME_AS_DETECTOR if shared else _entry_to_dict(features))
        return {
            "indices": list(detector.indices),
            "entries": [_entry_to_dict(e) for e in detector.entries],
            "pnp_keys": [] if self.pnp is None else list(self.pnp.features),
            "pnp_features": pnp_features,
            "last_loop_keyframe_count": self.last_loop_keyframe_count,
            "keyframes_seen": self.keyframes_seen,
            "rejected": self.rejected,
            "xfeat": None if self.pnp is None or self.pnp.xfeat is None else self.pnp.xfeat.state_dict(),
        }

    def load_state_dict(self, d: dict) -> None:
        self.detector.load([int(i) for i in d["indices"]], [_entry_from_dict(e) for e in d["entries"]])
        if self.pnp is not None:
            self.pnp.features = {
                int(k): self.detector.descriptor_of(int(k)) if f.get("kind") == "detector" else _entry_from_dict(f)
                for k, f in zip(d["pnp_keys"], d["pnp_features"])}
        self.last_loop_keyframe_count = int(d["last_loop_keyframe_count"])
        self.keyframes_seen = int(d["keyframes_seen"])
        self.rejected = int(d["rejected"])
        if self.pnp is not None and self.pnp.xfeat is not None and d.get("xfeat"):
            self.pnp.xfeat.load_state_dict(d["xfeat"])
