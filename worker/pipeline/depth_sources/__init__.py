"""Where a session's keyframe surfels come from: strategies chosen once, at its first frame.

- "sensor" (`SensorDepth`): the frames' own depth (RGB-D);
- "mvs" (`MultiViewDepth`): multi-view stereo on the tracked poses, built in the mapping stage (`StereoBuilder`);
- "model" (`ModelSurfels`): the learned model's prediction (with the frames' depth for the means when they carry
  it and `input.surfel_init` is "model", or when the poses are the model's own).

Each owns the keyframe jobs it made until the mapping stage takes them; jobs are data (worker.pipeline.map_jobs).
"""

from __future__ import annotations

from worker.pipeline.depth_sources.base import DepthSource
from worker.pipeline.depth_sources.model import ModelSurfels
from worker.pipeline.depth_sources.multiview import MultiViewDepth, StereoBuilder, stereo_builder
from worker.pipeline.depth_sources.sensor import SensorDepth

__all__ = ["DepthSource", "ModelSurfels", "MultiViewDepth", "SensorDepth", "StereoBuilder", "choose_depth_source",
           "stereo_builder"]


def choose_depth_source(requested: str, tracking: str, with_depth: bool) -> str:
    """Where keyframe surfels come from: the frames' depth, else `requested` ("auto": the model when it tracks,
    else multi-view stereo on the tracked poses)."""
    if with_depth:
        return "sensor"
    if requested == "auto":
        return "model" if tracking == "model" else "mvs"
    return requested
