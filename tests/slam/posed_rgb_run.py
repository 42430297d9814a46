"""A posed-RGB session (poses fixed, no depth, no refinement) over a few frames, for the multi-view depth tests."""

from __future__ import annotations

from worker.config import SlamConfig
from worker.slam import SlamSystem


def run_posed_rgb(frames, intrinsics, fill: str) -> SlamSystem:
    """The finished system after `frames`, with keyframe holes left as they are or filled by `fill`."""
    config = SlamConfig.preset("rgbd", threaded=False, input={"pose_mode": "fixed", "mvs_fill": fill},
                               mapping={"refine_iterations": 0, "final_refine_passes": 0})
    system = SlamSystem(config, intrinsics)
    for frame in frames:
        system.push(frame)
    system.finish()
    return system
