"""XFeat learned features (vendored network and weights, Apache-2.0: see NOTICE) for matching across wide baselines,
where optical flow and ORB fail."""

from .extractor import XFeatExtractor, XFeatures, mutual_matches

__all__ = ["XFeatExtractor", "XFeatures", "mutual_matches"]
