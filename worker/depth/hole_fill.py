"""Depth for the pixels multi-view stereo leaves without one (textureless walls, weak texture), propagated from
confident pixels on the same surface.

A pixel without depth takes the depth of a plane fitted to the confident pixels around it (inverse depth affine in
the pixel coordinates: any plane in 3-D), when
- those pixels have a colour like its own (the image is split into colour clusters; a pixel's support is the
  confident pixels of colours near its cluster's),
- they are enough (`min_support` window sides), spread in both directions around the pixel (`min_spread`,
  `max_offset`: the plane interpolates; it is not extrapolated from a line of pixels along an edge) and fit one
  plane (RMS residual below `max_residual` of the inverse depth: a window spanning two surfaces does not fill),
- the plane's depth there stays within the confident depths' range (widened by `depth_margin`).
Windows grow from the smallest radius to the largest; pixels filled in one pass support the next (`passes`), so
a hole fills from its border inwards up to about passes x the largest radius. Window sums come from integral
images, so the cost does not depend on the radius.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class HoleFillSettings:
    """How far and how cautiously depth is propagated into holes (pixels; fractions of inverse depth)."""

    radii: tuple[int, ...] = (4, 8, 16, 32)
    passes: int = 3
    min_support: float = 1.0  # confident pixels of a matching colour, in window sides (2 radius + 1 pixels)
    max_residual: float = 0.02  # RMS plane-fit residual relative to the fitted inverse depth
    colour_clusters: int = 8
    colour_distance: float = 0.1  # a cluster's support: confident pixels this close (RGB in [0, 1]) to its centre
    min_spread: float = 0.25  # the support's smallest standard deviation, as a fraction of the window radius
    max_offset: float = 2.0  # the pixel's Mahalanobis distance from the support's centre (standard deviations)
    depth_margin: float = 1.5
    work_side: int = 160  # larger images are filled at a reduced size (longer side about this; radii scale)


@dataclass
class FilledDepth:
    """depth: float32 [H, W], the confident depth plus the filled pixels (0 elsewhere); filled: bool [H, W]."""

    depth: np.ndarray
    filled: np.ndarray

    @property
    def fill_fraction(self) -> float:
        """Fraction of the image's pixels that were filled."""
        return float(self.filled.mean())


def fill_depth(depth: np.ndarray, image: np.ndarray, settings: HoleFillSettings | None = None,
               seed: int = 0) -> FilledDepth:
    """Fill the holes (depth 0) of `depth` [H, W] from confident neighbours of similar colour in `image` (uint8
    RGB [H, W, 3]); see the module docstring. `seed` fixes the colour clustering."""
    settings = settings or HoleFillSettings()
    depth = np.asarray(depth, np.float32)
    if image.shape[:2] != depth.shape or image.ndim != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 [H, W, 3] of the depth's size, got {image.dtype} {image.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    depth = np.where(valid, depth, 0).astype(np.float32)
    if valid.sum() < 3 or valid.all():
        return FilledDepth(depth, np.zeros(depth.shape, bool))
    H, W = depth.shape
    factor = max(1, round(max(H, W) / settings.work_side))
    if factor == 1:
        return _fill(depth, valid, image, settings, seed)
    # Fill a reduced copy (a pixel keeps a depth where its block's centre had one), then give the full-size holes
    # the reduced fill's depth; confident pixels keep theirs.
    size = (W // factor, H // factor)
    small = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
    small_image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    reduced = _fill(small, small > 0, small_image, settings, seed)
    up = cv2.resize(np.where(reduced.filled, reduced.depth, 0).astype(np.float32), (W, H),
                    interpolation=cv2.INTER_NEAREST)
    filled = ~valid & (up > 0)
    return FilledDepth(np.where(filled, up, depth).astype(np.float32), filled)


def _fill(depth: np.ndarray, valid: np.ndarray, image: np.ndarray, settings: HoleFillSettings, seed: int
          ) -> FilledDepth:
    """`fill_depth` at this size."""
    filled = np.zeros(depth.shape, bool)
    near, far = np.percentile(depth[valid], [1, 99])
    q_lo, q_hi = 1.0 / (settings.depth_margin * far), settings.depth_margin / near
    colours = image.astype(np.float32) / 255.0
    labels, centres = _colour_clusters(colours, settings.colour_clusters, seed)
    inverse = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    support = valid.copy()
    for _ in range(settings.passes):
        new = _fill_pass(inverse, support, colours, labels, centres, settings, (q_lo, q_hi))
        if not new.any():
            break
        filled |= new > 0
        inverse = np.where(new > 0, new, inverse)
        support |= new > 0
    out = np.where(valid, depth, np.where(filled, 1.0 / np.where(filled, inverse, 1.0), 0.0)).astype(np.float32)
    return FilledDepth(out, filled)


def _colour_clusters(colours: np.ndarray, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(cluster of each pixel [H, W] int, cluster centres [k, 3]) by k-means on a subsample of the pixels."""
    pixels = colours.reshape(-1, 3)
    sample = pixels[np.random.default_rng(seed).choice(len(pixels), min(len(pixels), 4000), replace=False)]
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 10, 1e-3)
    k = max(1, min(count, len(sample)))
    _, _, centres = cv2.kmeans(sample, k, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    distance = ((pixels[:, None, :] - centres[None]) ** 2).sum(-1)
    return distance.argmin(1).reshape(colours.shape[:2]), centres


def _fill_pass(inverse: np.ndarray, support: np.ndarray, colours: np.ndarray, labels: np.ndarray,
               centres: np.ndarray, settings: HoleFillSettings, q_range: tuple[float, float]) -> np.ndarray:
    """Inverse depth [H, W] of the pixels filled in this pass (0 elsewhere)."""
    H, W = inverse.shape
    new = np.zeros((H, W))
    holes = np.nonzero(~support)
    reach = max(settings.radii)  # only the holes' bounding box (and the windows around it) takes part
    y0, y1 = max(0, holes[0].min() - reach), min(H, holes[0].max() + reach + 1)
    x0, x1 = max(0, holes[1].min() - reach), min(W, holes[1].max() + reach + 1)
    box = (slice(y0, y1), slice(x0, x1))
    q, valid, colours, labels = inverse[box], support[box], colours[box], labels[box]
    h, w = q.shape
    scale = float(np.median(inverse[support]))
    v, u = np.mgrid[y0:y1, x0:x1].astype(np.float32)
    u, v = (u - W / 2) / 100.0, (v - H / 2) / 100.0  # well-conditioned moments
    qn = (q / scale).astype(np.float32)
    base = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v, qn, u * qn, v * qn, qn * qn], -1)
    for c, centre in enumerate(centres):
        targets = (labels == c) & ~valid
        if not targets.any():
            continue
        weight = valid & (((colours - centre) ** 2).sum(-1) <= settings.colour_distance ** 2)
        if weight.sum() < 3:
            continue
        integral = cv2.integral(base * weight[..., None].astype(np.float32), sdepth=cv2.CV_64F)
        rows, cols = np.nonzero(targets)
        for radius in settings.radii:
            if len(rows) == 0:
                break
            q_fit, ok = _plane_at(integral, rows, cols, u[rows, cols], v[rows, cols], radius, settings, h, w)
            q_fit = q_fit * scale
            ok &= (q_fit > q_range[0]) & (q_fit < q_range[1])
            new[rows[ok] + y0, cols[ok] + x0] = q_fit[ok]
            rows, cols = rows[~ok], cols[~ok]
    return new


def _plane_at(integral: np.ndarray, rows: np.ndarray, cols: np.ndarray, u: np.ndarray, v: np.ndarray,
              radius: int, settings: HoleFillSettings, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """(fitted normalised inverse depth at each pixel, whether the fit is trusted) from the window sums."""
    r0, r1 = np.clip(rows - radius, 0, H), np.clip(rows + radius + 1, 0, H)
    c0, c1 = np.clip(cols - radius, 0, W), np.clip(cols + radius + 1, 0, W)
    s = integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]  # [n, 10]
    n, su, sv, suu, suv, svv, sq, suq, svq, sqq = s.T
    A = np.stack([np.stack([suu, suv, su], -1), np.stack([suv, svv, sv], -1), np.stack([su, sv, n], -1)], -2)
    b = np.stack([suq, svq, sq], -1)
    enough = n >= np.maximum(settings.min_support * (2 * radius + 1), 6)
    # The support must spread in both directions (not a line of pixels along an edge) and surround the pixel
    # well enough that the plane interpolates rather than extrapolates.
    m = np.maximum(n, 1)
    mu, mv = su / m, sv / m
    cuu, cuv, cvv = suu / m - mu * mu, suv / m - mu * mv, svv / m - mv * mv
    half_trace = (cuu + cvv) / 2
    smallest = half_trace - np.sqrt(np.maximum(half_trace ** 2 - (cuu * cvv - cuv * cuv), 0.0))
    spread = settings.min_spread * radius / 100.0  # coordinates are in hundreds of pixels
    enough &= smallest >= spread ** 2
    du, dv = u - mu, v - mv
    det2 = np.maximum(cuu * cvv - cuv * cuv, 1e-18)
    mahalanobis2 = (cvv * du * du - 2 * cuv * du * dv + cuu * dv * dv) / det2
    enough &= mahalanobis2 <= settings.max_offset ** 2
    coef = np.zeros_like(b)
    if enough.any():
        coef[enough] = np.linalg.solve(A[enough], b[enough][..., None])[..., 0]
    a_u, a_v, a_c = coef.T
    fitted = a_u * u + a_v * v + a_c
    # residual sum of squares of the least-squares plane: sqq - coef . b
    rss = np.maximum(sqq - (coef * b).sum(-1), 0.0)
    rms = np.sqrt(rss / np.maximum(n, 1))
    ok = enough & (fitted > 0) & (rms <= settings.max_residual * np.abs(fitted))
    return fitted, ok
