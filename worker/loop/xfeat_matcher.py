"""XFeat matches between two keyframes, for loop verification where ORB's fail (a revisit from a wide viewpoint
change: ORB's descriptors change with the view, XFeat's learned ones much less).

Each keyframe's grey image is kept when it is added, at a long side of at most `max_side` pixels and JPEG-encoded
(320x240: ~12 kB instead of 77 kB raw, 300 kB for a 640x480 keyframe: a long session's loop closer and its snapshots
keep one per keyframe); its XFeat keypoints (in the keyframe's own pixels) and descriptors are
computed the first time a loop candidate needs them (one network pass, ~25 ms at 320x240 on one thread) and kept
for the `cached` keyframes used last. Matches are mutual nearest neighbours above a cosine similarity (XFeat's
matcher); the geometry (PnP on the old keyframe's points) is the relocalizer's (`worker.loop.pnp`).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import replace

import cv2
import numpy as np
import torch

from worker.tracking.xfeat import XFeatExtractor, XFeatures, mutual_matches, torch_threads


def grey_of(image: torch.Tensor) -> np.ndarray:
    """uint8 grey [H, W] of an image [1, 3, H, W] in [0, 1] (ITU-R BT.601 luma, as OpenCV's)."""
    rgb = image[0].detach().float().cpu()
    luma = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    return (luma * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()


class XFeatKeyframeMatcher:
    """Keyframe images and their XFeat features on demand (the network loads at the first use)."""

    def __init__(self, top_k: int = 1024, min_similarity: float = 0.82, threads: int = 1, cached: int = 32,
                 max_side: int = 320, jpeg_quality: int = 90) -> None:
        self.top_k, self.min_similarity, self.threads, self.cached = top_k, min_similarity, threads, cached
        self.max_side, self.jpeg_quality = max_side, jpeg_quality
        self.images: dict[int, tuple[bytes, float]] = {}  # keyframe -> (JPEG of its grey image, scale to it)
        self._features: OrderedDict[int, XFeatures] = OrderedDict()
        self._extractor: XFeatExtractor | None = None
        self.passes, self.seconds = 0, 0.0  # network passes so far and their time (what verification costs)

    def __contains__(self, index: int) -> bool:
        return int(index) in self.images

    def add_keyframe(self, index: int, image: torch.Tensor) -> None:
        """Keep keyframe `index`'s image [1, 3, H, W] in [0, 1] (as grey, downscaled, JPEG) for later matching."""
        grey = grey_of(image)
        scale = min(1.0, self.max_side / max(grey.shape))
        if scale < 1.0:
            size = (max(1, round(grey.shape[1] * scale)), max(1, round(grey.shape[0] * scale)))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        ok, encoded = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise ValueError(f"keyframe {index}: its image could not be encoded")
        self.images[int(index)] = (encoded.tobytes(), scale)

    def features(self, index: int) -> XFeatures:
        """XFeat keypoints and descriptors of keyframe `index` (computed once, kept for the newest uses)."""
        index = int(index)
        if index in self._features:
            self._features.move_to_end(index)
            return self._features[index]
        if self._extractor is None:
            self._extractor = XFeatExtractor(top_k=self.top_k)
        start = time.perf_counter()
        encoded, scale = self.images[index]
        grey = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_GRAYSCALE)
        with torch_threads(self.threads):
            found = self._extractor.extract(grey)
        if scale < 1.0:  # keypoints (pixel centres at +0.5) in the keyframe's own pixels
            found = replace(found, keypoints=(found.keypoints / scale).astype(found.keypoints.dtype))
        self.passes += 1
        self.seconds += time.perf_counter() - start
        self._features[index] = found
        while len(self._features) > self.cached:
            self._features.popitem(last=False)
        return found

    def match(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Matched pixels of keyframes i and j ([n, 2] each, pixel centres at +0.5)."""
        fi, fj = self.features(i), self.features(j)
        ia, ib = mutual_matches(fi.descriptors, fj.descriptors, self.min_similarity)
        return fi.keypoints[ia], fj.keypoints[ib]

    def state_dict(self) -> dict:
        keys = list(self.images)
        return {"keys": keys, "jpegs": [self.images[k][0] for k in keys],
                "scales": [self.images[k][1] for k in keys]}

    def load_state_dict(self, d: dict) -> None:
        self.images = {int(k): (bytes(jpeg), float(scale))
                       for k, jpeg, scale in zip(d["keys"], d.get("jpegs", []), d.get("scales", []))}
        self._features.clear()
