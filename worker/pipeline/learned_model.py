"""The learned model of a session (paper 4.1): loaded once, shared by the pose source, the surfels and loop closure."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch

from worker.config import SlamConfig
from worker.geometry import Intrinsics
from worker.tracking.sources import ModelTracking

log = logging.getLogger(__name__)


def load_model(config: SlamConfig) -> tuple[Any, str]:
    """(model, model id): the configured checkpoint, else a seeded random model (with a warning)."""
    from worker.frontend import build_model
    from worker.frontend.checkpoint import load_checkpoint

    fc = config.frontend
    path = config.checkpoint_path()
    if path is not None:
        return load_checkpoint(path, device=config.device), f"checkpoint:{path.name}"
    log.warning("no checkpoint for model %r: using a randomly initialised model (seed %d); poses and maps will be "
                "meaningless until trained weights are given", fc.model, fc.seed)
    with torch.random.fork_rng():
        torch.manual_seed(fc.seed)
        model = build_model(fc.model, device=config.device)
    return model, f"random:{fc.model}:seed={fc.seed}"


def custom_model(config: SlamConfig) -> bool:
    """Whether the configured model is the user's (weights other than the shipped synthetic ones)."""
    return bool(config.frontend.checkpoint) or config.frontend.model != "tiny"


@dataclass
class LearnedModel:
    """The model with its submap tracker and bag of hidden states, and the model as a pose source."""

    model: Any
    model_id: str
    tracker: Any  # worker.frontend.tracker.SubmapTracker
    bag: Any  # worker.loop.bag.HiddenStateBag
    tracking: ModelTracking
    long_side: int

    @classmethod
    def build(cls, config: SlamConfig, loaded: tuple[Any, str] | None = None) -> LearnedModel:
        """The session's model (`loaded`: one loaded already), tracker and bag."""
        from worker.frontend.tracker import SubmapTracker, TrackerConfig
        from worker.loop.bag import HiddenStateBag

        fc = config.frontend
        model, model_id = loaded or load_model(config)
        tracker = SubmapTracker(model, TrackerConfig(submap_length=fc.submap_size,
                                                     keyframe_translation=fc.keyframe_depth_ratio,
                                                     keyframe_rotation_deg=fc.keyframe_rotation_deg))
        bag = HiddenStateBag()
        return cls(model, model_id, tracker, bag, ModelTracking(tracker, bag, fc.long_side, _estimate_intrinsics),
                   fc.long_side)

    @property
    def intrinsics(self) -> Intrinsics | None:
        """The camera at model resolution (given or estimated)."""
        return self.tracking.model_intrinsics

    def intrinsics_at(self, width: int, height: int) -> Intrinsics | None:
        """The model's camera back at the input resolution `width` x `height` (undo the centre crop, then the
        resize)."""
        from worker.frontend.preprocess import centre_crop_box, resized_size

        intr = self.intrinsics
        if intr is None:
            return None
        new_w, new_h = resized_size(width, height, self.long_side)
        scale = new_w / width
        left, top, _, _ = centre_crop_box(new_w, new_h)
        return Intrinsics(intr.fx / scale, intr.fy / scale, (intr.cx + left) / scale, (intr.cy + top) / scale, width,
                          height)


def _estimate_intrinsics(surfels, prep) -> Intrinsics:
    from worker.frontend.focal import estimate_focal, intrinsics_from_focal

    h, w = prep.tensor.shape[-2:]
    focal = estimate_focal(surfels.points.float(), surfels.conf.float())
    intr = intrinsics_from_focal(focal, w, h)
    log.info("estimated focal length %.1f px at %dx%d", focal, w, h)
    return intr
