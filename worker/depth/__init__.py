"""Multi-view depth for keyframes with known poses: plane-sweep stereo (ZNCC, semi-global aggregation, parabola
refinement, multi-view consistency) for posed-RGB phones and monocular keyframes, with no learned model.

`estimate_depth` is the entry point; `select_neighbours` picks the frames to match against; `scale_to_confident`
brings another depth map (the model's) to the scale of the confident pixels; `cross_check` compares two keyframes'
depth maps geometrically (left-right check).
"""

from .config import MultiViewDepthConfig
from .consistency import cross_check
from .estimate import DepthEstimate, estimate_depth
from .neighbours import select_neighbours
from .scale import confident_scale, scale_to_confident

__all__ = ["DepthEstimate", "MultiViewDepthConfig", "confident_scale", "cross_check", "estimate_depth",
           "scale_to_confident", "select_neighbours"]
