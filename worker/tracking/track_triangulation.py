"""New map points from optical-flow tracks: a candidate track is triangulated between the oldest keyframe of the
window that saw it and the newest keyframe, once the two rays meet at a wide enough angle; one whose rays are wide
but miss each other (it does not reproject in both views) drifted or jumped, and is reported for removal."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .local_map import Keyframe
from .tracks import lookup_sorted
from .triangulation import good_points, parallax_cos, triangulate


@dataclass
class TrackPoints:
    """Track ids [n] (sorted) and world points [n, 3] of the new points; ids [m] of the tracks to drop."""

    ids: np.ndarray
    points: np.ndarray
    inconsistent: np.ndarray


def triangulate_tracks(keyframes: list[Keyframe], ids: np.ndarray, uv: np.ndarray, K: np.ndarray, chi2: float,
                       min_parallax_deg: float) -> TrackPoints:
    """Points of the candidate tracks `ids` [N] seen at pixels `uv` [N, 2] by the newest of `keyframes` (oldest
    first); chi2 bounds the squared reprojection error in pixels (one-pixel noise)."""
    newest = keyframes[-1]
    anchored = np.zeros(len(ids), bool)
    new_ids, new_points, drop = [np.zeros(0, np.int64)], [np.zeros((0, 3))], [np.zeros(0, np.int64)]
    for other in keyframes[:-1]:
        order = np.argsort(other.track_ids)
        at, found = lookup_sorted(other.track_ids[order], ids)
        sel = found & ~anchored
        if not sel.any():
            continue
        anchored |= sel
        uv_a = other.features.keypoints[order[at[sel]]].astype(np.float64)
        uv_b = uv[sel].astype(np.float64)
        points = triangulate(other.pose, newest.pose, uv_a, uv_b, K)
        ones = np.ones(len(uv_a))
        consistent = good_points(points, other.pose, newest.pose, uv_a, uv_b, ones, ones, K, chi2, 0.0)
        wide = parallax_cos(np.nan_to_num(points), other.pose, newest.pose) < np.cos(np.deg2rad(min_parallax_deg))
        new_ids.append(ids[sel][consistent & wide])
        new_points.append(points[consistent & wide])
        drop.append(ids[sel][~consistent & wide])
    out_ids = np.concatenate(new_ids)
    order = np.argsort(out_ids)
    return TrackPoints(out_ids[order], np.concatenate(new_points)[order], np.concatenate(drop))
