"""Appearance descriptors for loop detection, two behind one interface.

* `EncoderGeMDescriptor`: GeM pooling of our own encoder tokens (model.encode_image). Tokens are signed, so the
  positive and negative parts are pooled separately and concatenated, then L2-normalised; similarity is the
  cosine. No extra weights, one encoder pass per keyframe.
* `OrbDescriptor`: classical, needs no weights: ORB keypoints through OpenCV, direct descriptor matching with
  Lowe's ratio test, then RANSAC on the fundamental matrix; similarity is the fraction of geometrically
  consistent matches. Its bags of words under a visual vocabulary (worker.loop.vocabulary) let the loop detector
  rank the database through an inverted index, so that only a short list is verified geometrically and the query
  cost stays flat as the map grows. Its features are also what the PnP relocalizer matches.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol

import cv2
import numpy as np
import torch

from .vocabulary import DEFAULT_PATH, SparseBag, Vocabulary


class GlobalDescriptor(Protocol):
    """A keyframe descriptor. One that also has a `vocabulary` and `words_of(descriptor) -> SparseBag` lets the
    loop detector rank its database through an inverted index."""

    name: str

    def describe(self, image: torch.Tensor) -> Any:
        """Descriptor of one keyframe image [1,3,H,W] in [0,1]."""

    def similarities(self, query: Any, database: list[Any]) -> np.ndarray:
        """Scores in [0,1] of `query` against each database entry (higher = more alike)."""


def _check_image(image: torch.Tensor) -> None:
    if image.ndim != 4 or image.shape[0] != 1 or image.shape[1] != 3:
        raise ValueError(f"descriptors take one image [1,3,H,W], got {tuple(image.shape)}")


class EncoderGeMDescriptor:
    """Generalised-mean pooled encoder tokens (signed GeM), L2-normalised."""

    name = "encoder_gem"

    def __init__(self, model, p: float = 3.0) -> None:
        if p < 1:
            raise ValueError(f"GeM power must be >= 1, got {p}")
        self.model = model
        self.p = p

    @torch.no_grad()
    def describe(self, image: torch.Tensor) -> torch.Tensor:
        _check_image(image)
        tokens, _ = self.model.encode_image(image)
        x = tokens[0].float()
        x = x - x.mean(dim=0, keepdim=True).mean(dim=1, keepdim=True)  # remove the global offset, keep structure

        def gem(v: torch.Tensor) -> torch.Tensor:
            return v.clamp_min(1e-6).pow(self.p).mean(dim=0).pow(1.0 / self.p)

        d = torch.cat([gem(x), gem(-x)])
        return d / d.norm().clamp_min(1e-12)

    def similarities(self, query: torch.Tensor, database: list[torch.Tensor]) -> np.ndarray:
        if not database:
            return np.zeros(0)
        return (torch.stack(database) @ query).clamp(0, 1).numpy().astype(np.float64)


@dataclass
class OrbFeatures:
    """ORB keypoints [N,2] (x, y pixels) and binary descriptors [N,32] of one image of width x height; `words` is
    the sparse tf-idf bag of words under the descriptor's vocabulary (filled on first use)."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    width: int
    height: int
    words: SparseBag | None = None

    def __len__(self) -> int:
        return len(self.keypoints)


def to_gray_uint8(image: torch.Tensor) -> np.ndarray:
    """[1,3,H,W] float in [0,1] -> H x W uint8 grey."""
    _check_image(image)
    rgb = (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


@lru_cache(maxsize=1)
def default_vocabulary() -> Vocabulary:
    """The shipped ORB vocabulary (loaded once per process)."""
    return Vocabulary.load(DEFAULT_PATH)


class OrbDescriptor:
    """ORB + ratio-test matching + fundamental-matrix RANSAC (MAGSAC++); score = inliers / min(#features).

    `vocabulary` (the shipped one by default) gives each keyframe's bag of words, which the loop detector's
    inverted index ranks the database with; None leaves the detector to verify every entry.
    """

    name = "orb"

    def __init__(self, n_features: int = 1000, ratio: float = 0.8, ransac_px: float = 2.0,
                 min_matches: int = 12, vocabulary: Vocabulary | None | str = "default") -> None:
        self.vocabulary = default_vocabulary() if vocabulary == "default" else vocabulary
        self.n_features = n_features
        self._orbs: dict[int, cv2.ORB] = {}
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.ratio = ratio
        self.ransac_px = ransac_px
        self.min_matches = min_matches

    def _orb_for(self, height: int, width: int) -> cv2.ORB:
        # OpenCV's 31-pixel patch wastes most of a small image's border; shrink it for low resolutions.
        patch = 31 if min(height, width) >= 300 else 15
        if patch not in self._orbs:
            self._orbs[patch] = cv2.ORB_create(nfeatures=self.n_features, edgeThreshold=patch, patchSize=patch,
                                               fastThreshold=10)
        return self._orbs[patch]

    def describe(self, image: torch.Tensor) -> OrbFeatures:
        gray = to_gray_uint8(image)
        kps, desc = self._orb_for(*gray.shape).detectAndCompute(gray, None)
        pts = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
        desc = np.zeros((0, 32), np.uint8) if desc is None else desc
        return OrbFeatures(pts, desc, gray.shape[1], gray.shape[0])

    def match(self, a: OrbFeatures, b: OrbFeatures, ratio: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Indices (ia, ib) of ratio-test matches from a to b (ratio defaults to the descriptor's)."""
        ratio = self.ratio if ratio is None else ratio
        if len(a) < 2 or len(b) < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pairs = self.matcher.knnMatch(a.descriptors, b.descriptors, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < ratio * m[1].distance]
        return (np.array([m.queryIdx for m in good], np.int64), np.array([m.trainIdx for m in good], np.int64))

    def geometric_matches(self, a: OrbFeatures, b: OrbFeatures) -> tuple[np.ndarray, np.ndarray]:
        """Matches that survive RANSAC on the fundamental matrix (empty when too few)."""
        ia, ib = self.match(a, b)
        if len(ia) < self.min_matches:
            return ia[:0], ib[:0]
        # MAGSAC++ (OpenCV's USAC) finds as many inliers as plain RANSAC or more at a tenth of its time on a query's
        # shortlist: plain RANSAC ran to its 1,000 iterations on every candidate that is no revisit
        _, mask = cv2.findFundamentalMat(a.keypoints[ia], b.keypoints[ib], cv2.USAC_MAGSAC, self.ransac_px, 0.999)
        if mask is None:
            return ia[:0], ib[:0]
        keep = mask.ravel().astype(bool)
        return ia[keep], ib[keep]

    def words_of(self, features: OrbFeatures) -> SparseBag | None:
        """The features' sparse bag of words (computed once and kept on them); None without a vocabulary."""
        if self.vocabulary is None:
            return None
        if features.words is None:
            features.words = self.vocabulary.sparse_bag(features.descriptors)
        return features.words

    def similarities(self, query: OrbFeatures, database: list[OrbFeatures]) -> np.ndarray:
        """Geometric verification of the query against every given entry (the caller shortlists)."""
        scores = np.zeros(len(database))
        for n, entry in enumerate(database):
            ia, _ = self.geometric_matches(query, entry)
            scores[n] = len(ia) / max(1, min(len(query), len(entry)))
        return scores
