"""XFeat learned features (vendored network and weights, Apache-2.0: see NOTICE) for matching across wide baselines,
where optical flow and ORB fail."""

from .extractor import DescriptorMap, XFeatExtractor, XFeatures, mutual_matches
from .threads import torch_threads

__all__ = ["DescriptorMap", "XFeatExtractor", "XFeatures", "mutual_matches", "torch_threads"]
