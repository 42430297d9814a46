"""The offset between a device's pose clock and the camera's, measured from the images.

A phone (ARKit/ARCore) or a motion-capture system stamps its poses with a clock that differs from the camera's by
tens of milliseconds: the pose a frame carries is really the camera's pose at `timestamp + offset`. The images' own
frame-to-frame motion is free of that clock. Corners are tracked between consecutive frames (pyramidal LK, checked
both ways); for each candidate offset d on a 1 ms grid the device trajectory is read at `t - d` for both frames of
every pair (worker.tracking.pose_interpolation), and its relative motion is scored against the tracks directly:
with depth, the reprojection error of the previous frame's back-projected corners; without, their Sampson distance to
the epipolar lines (scale-free). Both are truncated (a wrong track costs the same at every offset). The offset is
the minimum of the summed cost (refined by a parabola); its uncertainty the spread of that minimum over bootstrap
resamples of the frame pairs. It is trusted only when that spread is small and the minimum lies inside the search
range: a stream without motion (every offset fits equally) is "not estimated".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from worker.tracking.optical_flow import track_points
from worker.tracking.pose_interpolation import interpolate_poses

MAX_CORNERS = 120  # corners per pair: the cost is a median-like mean, more add little
MIN_TRACKS = 15  # a pair with fewer tracked corners is not kept
TRUNCATE_PX = {True: 3.0, False: 2.0}  # with depth (reprojection) / without (epipolar): beyond it a track is wrong
MIN_FLOW_PX = 0.5  # a pair whose corners moved less (median) shows nothing of the offset: not kept
MAX_PAIRS = 240  # the newest pairs kept (a snapshot carries them while measuring)
BOOTSTRAP = 200
COARSE_STEP_S = 0.005  # the first pass over the search range, refined around its minimum


def _with_corners(t: float, grey: np.ndarray, depth: np.ndarray | None
                  ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
    """A frame as the next one tracks from: its time, grey image, corners and their depth (None without depth)."""
    corners = cv2.goodFeaturesToTrack(grey, MAX_CORNERS, 0.01, 8)
    uv = np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2) + np.float32(0.5)
    if depth is None:
        return t, grey, uv, None
    col = np.clip(uv[:, 0].astype(int), 0, depth.shape[1] - 1)
    row = np.clip(uv[:, 1].astype(int), 0, depth.shape[0] - 1)
    return t, grey, uv, np.asarray(depth[row, col], np.float64)


@dataclass
class FramePair:
    """Corners tracked from one frame (at `t0`) into the next (at `t1`): normalised image coordinates [n, 2] in
    both, the depth of the first ones [n] (NaN without depth), float32; the focal length (pixels per unit of them)."""

    t0: float
    t1: float
    x0: np.ndarray
    x1: np.ndarray
    depth: np.ndarray
    focal: float

    def to_state(self) -> list[Any]:
        return [self.t0, self.t1, self.x0, self.x1, self.depth, self.focal]

    @classmethod
    def from_state(cls, state: list[Any]) -> FramePair:
        t0, t1, x0, x1, depth, focal = state
        return cls(float(t0), float(t1), np.asarray(x0, np.float32).reshape(-1, 2),
                   np.asarray(x1, np.float32).reshape(-1, 2), np.asarray(depth, np.float32).ravel(), float(focal))


class PairTracker:
    """Tracks corners from each frame into the next and keeps the pairs that show motion (see the module docstring);
    the newest MAX_PAIRS of them."""

    def __init__(self, max_gap_s: float = 0.1) -> None:
        self.max_gap_s = max_gap_s
        self.pairs: list[FramePair] = []
        # the previous frame: (t, grey, its corners [n, 2] (pixel centres at +0.5), their depth [n] or None)
        self._previous: tuple[float, np.ndarray, np.ndarray, np.ndarray | None] | None = None

    def add(self, timestamp: float, image: np.ndarray, depth: np.ndarray | None, K: np.ndarray) -> None:
        """The previous frame's corners tracked into this one (none across a gap longer than `max_gap_s`); this
        frame's corners (and their depth) kept for the next."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        previous, self._previous = self._previous, _with_corners(timestamp, grey, depth)
        if previous is None or not 0 < timestamp - previous[0] <= self.max_gap_s or len(previous[2]) < MIN_TRACKS:
            return
        t0, grey0, uv0, z0 = previous
        uv1, ok = track_points(grey0, grey, uv0)
        z = np.full(len(uv0), np.nan) if z0 is None else z0
        if z0 is not None:
            ok &= z > 0
        if ok.sum() < MIN_TRACKS or np.median(np.linalg.norm(uv1[ok] - uv0[ok], axis=1)) < MIN_FLOW_PX:
            return
        Kinv = np.linalg.inv(K)

        def normalised(uv: np.ndarray) -> np.ndarray:
            return (np.c_[uv, np.ones(len(uv))] @ Kinv.T)[:, :2].astype(np.float32)

        # float32: what a snapshot carries while measuring (a restored session measures the same)
        self.pairs.append(FramePair(t0, timestamp, normalised(uv0[ok]), normalised(uv1[ok]),
                                    z[ok].astype(np.float32), float(np.sqrt(K[0, 0] * K[1, 1]))))
        del self.pairs[:-MAX_PAIRS]

    def state_dict(self) -> dict[str, Any]:
        t, grey, uv, z = self._previous if self._previous is not None else (None, None, None, None)
        return {"pairs": [p.to_state() for p in self.pairs], "previous_t": t, "previous_grey": grey,
                "previous_corners": uv, "previous_depth": z}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pairs = [FramePair.from_state(p) for p in state["pairs"]]
        grey, z = state.get("previous_grey"), state.get("previous_depth")
        self._previous = None if grey is None or state.get("previous_corners") is None else (
            float(state["previous_t"]), np.asarray(grey, np.uint8),
            np.asarray(state["previous_corners"], np.float32).reshape(-1, 2),
            None if z is None else np.asarray(z, np.float64).ravel())

    def forget_previous(self) -> None:
        """The next frame starts a new run of pairs (a frame without a device pose came between)."""
        self._previous = None


@dataclass(frozen=True)
class ClockEstimate:
    """The measured offset (seconds, None: not estimated, with why in `reason`), its uncertainty (seconds) and the
    frame pairs it rests on."""

    offset_s: float | None
    uncertainty_s: float | None
    pairs: int
    reason: str

    def to_dict(self) -> dict[str, Any]:
        def ms(value: float | None) -> float | None:
            return None if value is None else round(value * 1000.0, 2)

        return {"estimated": self.offset_s is not None, "offset_ms": ms(self.offset_s),
                "uncertainty_ms": ms(self.uncertainty_s), "pairs": self.pairs, "reason": self.reason}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ClockEstimate:
        def s(value: float | None) -> float | None:
            return None if value is None else float(value) / 1000.0

        return cls(s(data["offset_ms"]), s(data["uncertainty_ms"]), int(data["pairs"]), str(data["reason"]))


def offset_costs(pairs: list[FramePair], times: np.ndarray, poses: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """[pairs, offsets]: each pair's mean truncated squared error (pixels^2) with the device trajectory (`times`,
    `poses` c2w) read at `t - offset` for each offset."""
    costs = np.zeros((len(pairs), len(offsets)))
    for n, pair in enumerate(pairs):
        queries = np.stack([pair.t0 - offsets, pair.t1 - offsets], axis=1)  # [G, 2]
        P = interpolate_poses(times, poses, queries)
        A = np.linalg.inv(P[:, 1]) @ P[:, 0]  # first camera -> second camera, [G, 4, 4]
        R, t = A[:, :3, :3], A[:, :3, 3]
        h0 = np.c_[pair.x0, np.ones(len(pair.x0))]  # [M, 3]
        with_depth = bool(np.all(np.isfinite(pair.depth)))
        if with_depth:
            X = np.einsum("gij,mj->gmi", R, h0 * pair.depth[:, None]) + t[:, None, :]
            z = X[..., 2]
            proj = X[..., :2] / np.where(z > 1e-6, z, np.nan)[..., None]
            err2 = ((proj - pair.x1[None]) ** 2).sum(-1) * pair.focal ** 2
        else:
            err2 = _sampson2(R, t, h0, pair.x1) * pair.focal ** 2
        cap = TRUNCATE_PX[with_depth] ** 2
        costs[n] = np.minimum(np.nan_to_num(err2, nan=cap), cap).mean(axis=1)
    return costs


def _sampson2(R: np.ndarray, t: np.ndarray, h0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """[G, M] squared Sampson distances (normalised units) of the tracks under motions (R [G,3,3], t [G,3]); where a
    motion has no translation, the squared transfer error of the rotation alone."""
    norm = np.linalg.norm(t, axis=1, keepdims=True)
    direction = t / np.maximum(norm, 1e-12)
    tx = np.zeros((len(t), 3, 3))
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -direction[:, 2], direction[:, 1], -direction[:, 0]
    tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = direction[:, 2], -direction[:, 1], direction[:, 0]
    E = tx @ R
    h1 = np.c_[x1, np.ones(len(x1))]
    Ex0 = np.einsum("gij,mj->gmi", E, h0)
    Etx1 = np.einsum("gji,mj->gmi", E, h1)
    num = np.einsum("mi,gmi->gm", h1, Ex0) ** 2
    den = Ex0[..., 0] ** 2 + Ex0[..., 1] ** 2 + Etx1[..., 0] ** 2 + Etx1[..., 1] ** 2
    sampson = num / np.maximum(den, 1e-18)
    rotated = np.einsum("gij,mj->gmi", R, h0)
    transfer = ((rotated[..., :2] / rotated[..., 2:3] - x1[None]) ** 2).sum(-1)
    return np.where(norm > 1e-9, sampson, transfer)


def _refined_minimum(cost: np.ndarray, offsets: np.ndarray) -> tuple[int, float]:
    """(index, offset) of the minimum of `cost` over increasing `offsets`, refined by the parabola through it and its
    neighbours."""
    i = int(np.argmin(cost))
    if 0 < i < len(cost) - 1:
        x, y = offsets[i - 1:i + 2] - offsets[i], cost[i - 1:i + 2]
        a, b, _ = np.polyfit(x, y, 2)
        if a > 0:
            return i, float(offsets[i] + np.clip(-b / (2 * a), x[0], x[2]))
    return i, float(offsets[i])


def estimate_offset(pairs: list[FramePair], times: np.ndarray, poses: np.ndarray, search_s: float = 0.1,
                    max_uncertainty_s: float = 0.005, min_pairs: int = 20, step_s: float = 0.001) -> ClockEstimate:
    """The device clock's offset from the frame pairs and the device's trajectory (`times`, c2w `poses`) received
    with them (module docstring). Pairs whose re-timed reads would leave the trajectory are not used."""
    times = np.asarray(times, np.float64)
    usable = [p for p in pairs if len(times) and p.t0 - search_s >= times[0] and p.t1 + search_s <= times[-1]]
    if len(usable) < min_pairs:
        return ClockEstimate(None, None, len(usable),
                             f"{len(usable)} frame pairs with motion and tracked corners, fewer than {min_pairs}")
    # A coarse grid over the search range, then every `step_s` around its minimum
    coarse = np.linspace(-search_s, search_s, 2 * int(round(search_s / COARSE_STEP_S)) + 1)
    coarse_costs = offset_costs(usable, times, poses, coarse)
    centre = coarse[int(np.argmin(coarse_costs.sum(axis=0)))]
    fine = centre + np.arange(-COARSE_STEP_S, COARSE_STEP_S + step_s / 2, step_s)
    fine = fine[(fine > -search_s) & (fine < search_s) & ~np.isin(np.round(fine, 6), np.round(coarse, 6))]
    offsets = np.concatenate([coarse, fine])
    order = np.argsort(offsets)
    offsets = offsets[order]
    costs = np.concatenate([coarse_costs, offset_costs(usable, times, poses, fine)], axis=1)[:, order]
    total = costs.sum(axis=0)
    i, offset = _refined_minimum(total, offsets)
    if i <= 1 or i >= len(offsets) - 2:
        return ClockEstimate(None, None, len(usable),
                             f"no minimum within +-{search_s * 1000:.0f} ms (the motion does not show the offset)")
    rng = np.random.default_rng(0)  # deterministic: the same frames give the same verdict
    weights = rng.multinomial(len(usable), np.full(len(usable), 1.0 / len(usable)), size=BOOTSTRAP)
    resampled = [_refined_minimum(row, offsets)[1] for row in weights @ costs]
    spread = float(np.std(resampled))
    if spread > max_uncertainty_s:
        return ClockEstimate(None, spread, len(usable),
                             f"uncertainty {spread * 1000:.1f} ms above {max_uncertainty_s * 1000:.1f} ms: the "
                             f"motion does not show the offset clearly")
    return ClockEstimate(offset, spread, len(usable),
                         f"measured on {len(usable)} frame pairs: {offset * 1000:.1f} +- {spread * 1000:.1f} ms")
