"""Which archived keyframe image a full archive lets go: the one whose view another held keyframe sees most nearly.

A long session holds more keyframe images than the archive may keep. Halving the archive whenever it overflows (the
first rule) dropped every second view however far apart they were: 124 keyframes over a desk kept 33-64 images for
the final refinement and the held-out views between the dropped ones rendered 2 dB worse. Here one image goes at a
time, the most redundant: the archived keyframe whose nearest held neighbour (any held keyframe, the window's
included) is nearest in view distance, the distance between the camera centres over the scene's depth plus the
angle between the optical axes (radians). A camera that lingers or comes back over the same place gives up its
images first; the views only it saw stay. Ties go to the oldest.
"""

from __future__ import annotations

import numpy as np


def view_distances(centres: np.ndarray, axes: np.ndarray, scene_depth: float) -> np.ndarray:
    """[N, N] view distance between N cameras: centre distance / `scene_depth` + angle between optical axes (rad),
    the diagonal infinite. `centres` [N, 3] and unit `axes` [N, 3] in world coordinates."""
    depth = max(float(scene_depth), 1e-9)
    offsets = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=-1) / depth
    angles = np.arccos(np.clip(axes @ axes.T, -1.0, 1.0))
    distances = offsets + angles
    np.fill_diagonal(distances, np.inf)
    return distances


def most_redundant(centres: np.ndarray, axes: np.ndarray, candidates: list[int], scene_depth: float) -> int:
    """The index (into `centres`) among `candidates` of the camera whose nearest other camera is nearest (the
    first, i.e. oldest, of equals)."""
    if not candidates:
        raise ValueError("no candidate keyframe to let go")
    nearest = view_distances(centres, axes, scene_depth).min(axis=1)
    return min(candidates, key=lambda i: (nearest[i], i))


def thin(centres: np.ndarray, axes: np.ndarray, candidates: list[int], keep: int, scene_depth: float) -> list[int]:
    """The candidates to let go, one at a time the most redundant, until at most `keep` remain (the other cameras
    stay as neighbours throughout)."""
    remaining = list(range(len(centres)))
    pool = list(candidates)
    dropped: list[int] = []
    while len(pool) > keep:
        local = most_redundant(centres[remaining], axes[remaining], [remaining.index(c) for c in pool], scene_depth)
        victim = remaining[local]
        dropped.append(victim)
        pool.remove(victim)
        remaining.remove(victim)
    return dropped
