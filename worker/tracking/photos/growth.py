"""How a newly registered photo grows the reconstruction: its matches to points other photos see join those points
(where they reproject), and its matches between keypoints that see no point yet become new points."""

from __future__ import annotations

import numpy as np

from ..projection import project
from ..triangulation import good_points, triangulate
from .reconstruction import Reconstruction

Matches = dict[int, tuple[np.ndarray, np.ndarray]]  # other photo's slot -> (its keypoints, the new photo's)


def reprojects(m: Reconstruction, K: np.ndarray, chi2_px: float, slot: int, keypoints: np.ndarray,
               points: np.ndarray) -> np.ndarray:
    """Mask of the points that project in front of photo `slot` within chi2_px (squared pixels) of its keypoints."""
    photo = m.photos[slot]
    uv, z = project(m.points[points], photo.pose, K)
    return (z > 0) & (((uv - photo.features.keypoints[keypoints]) ** 2).sum(1) < chi2_px)


def join_known_points(m: Reconstruction, K: np.ndarray, chi2_px: float, slot: int, matches: Matches) -> None:
    """Photo `slot`'s keypoints without a point, matched to points of other photos, see those points where they
    reproject (a revisit ties the new photo to the old points)."""
    photo = m.photos[slot]
    for other, (i_old, i_new) in matches.items():
        point = m.photos[other].point_of[i_old]
        use = (point >= 0) & (photo.point_of[i_new] < 0)
        if use.any():
            ok = reprojects(m, K, chi2_px, slot, i_new[use], point[use])
            m.observe(slot, i_new[use][ok], point[use][ok])


def triangulate_matches(m: Reconstruction, K: np.ndarray, chi2_px: float, min_parallax_deg: float, slot: int,
                        matches: Matches) -> None:
    """New points from photo `slot`'s matches whose keypoints see no point yet (seen under `min_parallax_deg` or
    more, reprojecting in both photos); a match whose new keypoint already sees one extends that point's track to
    the other photo where it reprojects."""
    photo = m.photos[slot]
    for other, (i_old, i_new) in matches.items():
        old = m.photos[other]
        free_old = old.point_of[i_old] < 0
        extend = free_old & (photo.point_of[i_new] >= 0)
        if extend.any():
            ok = reprojects(m, K, chi2_px, other, i_old[extend], photo.point_of[i_new[extend]])
            m.observe(other, i_old[extend][ok], photo.point_of[i_new[extend]][ok])
        both = free_old & (photo.point_of[i_new] < 0)
        if not both.any():
            continue
        ia, ib = i_old[both], i_new[both]
        uv_a, uv_b = old.features.keypoints[ia], photo.features.keypoints[ib]
        ones = np.ones(len(ia))
        X = triangulate(old.pose, photo.pose, uv_a, uv_b, K)
        good = good_points(X, old.pose, photo.pose, uv_a, uv_b, ones, ones, K, chi2_px, min_parallax_deg)
        if good.any():
            ids = m.add_points(X[good])
            m.observe(other, ia[good], ids)
            m.observe(slot, ib[good], ids)
