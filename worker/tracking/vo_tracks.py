"""Visual odometry's tracks: points followed from the last tracked frame by optical flow, and new corners added
where the tracks are sparse."""

from __future__ import annotations

import numpy as np

from .optical_flow import detect_corners, track_points
from .vo_state import VoParts, VoState


def flow(s: VoState, parts: VoParts, gray: np.ndarray, guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The tracks' pixels [N, 2] in `gray` followed from the last tracked frame (`guess`: where the motion model
    puts them) and which of them were followed [N]."""
    c = parts.config
    return track_points(s.previous_gray, gray, s.tracks.uv, guess, window=c.flow_window,
                        levels=c.flow_levels, max_fb_px=c.flow_fb_px)


def replenish(s: VoState, parts: VoParts, gray: np.ndarray) -> None:
    """New candidate tracks at corners away from the existing ones, up to `max_tracks`."""
    c = parts.config
    corners = detect_corners(gray, s.tracks.uv, c.max_tracks - len(s.tracks),
                             c.corner_min_distance * max(gray.shape), c.corner_quality)
    ids = np.arange(s.next_id, s.next_id + len(corners), dtype=np.int64)
    s.next_id += len(corners)
    s.tracks = s.tracks.extend(ids, corners)
