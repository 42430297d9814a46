"""Close the holes a keyframe's view of the map still has, and a margin past its border, from the map's own
geometry: the end-of-run step before the final refinement (`GaussianMap.close_holes`).

Multi-view stereo gives no depth where fewer than two views see a pixel: the border band of every keyframe, where
only that keyframe looked, and surfaces no neighbour matched. Views between keyframes then see holes there (on
sparse photos around an object, the photo borders). Each held keyframe's camera, widened by `margin` of its image
on every side, renders the map; pixels it leaves uncovered (alpha below `max_alpha`) get a surfel at the inverse depth
of the plane fitted around their nearest covered pixel (a wall seen at an angle continues as one), coloured by the
keyframe's photo inside its frame and by the render inpainted (Telea) past it. The surfels
face the camera, one per `1 / resolution` pixels, and start at `opacity`, so the final refinement trains them with
the rest of the map wherever a keyframe sees them. Only holes within `reach` of a covered pixel are closed, and only
in views whose frame the map covers at least `min_covered`: a keyframe the map barely reaches (stereo failed on it)
would otherwise extrapolate a few pixels into a sheet of guessed depth hanging in front of other views.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from .rasterize import RenderResult
from .surfels import Surfels

# A closing surfel's standard deviation in pixels of the closing resolution (spaced one pixel apart, neighbours
# overlap enough that the closed region renders with alpha above 0.7 everywhere).
SIGMA_PIXELS = 0.6
# Extrapolated inverse depth stays within the covered pixels' range widened by this factor on both sides.
RANGE_MARGIN = 1.5


@dataclass(frozen=True)
class HoleClosingSettings:
    """How far past a keyframe's border and how finely the holes of its view are closed."""

    margin: float = 0.1  # the view is widened by this fraction of the image's width and height on every side
    reach: float = 0.1  # holes are closed up to this fraction of the image's shorter side from a covered pixel
    min_covered: float = 0.5  # views whose own frame the map covers less than this are left as they are
    max_alpha: float = 0.5  # pixels the map covers less than this are holes
    resolution: float = 0.5  # holes are closed at this fraction of the keyframe's resolution
    opacity: float = 0.95  # as a keyframe's own new surfels: the refinement fades them where the photos disagree
    inpaint_radius: int = 4  # colours: pixels (at the closing resolution) that inform each inpainted pixel
    plane_radius: int = 6  # inverse depth: window radius of the plane fitted around a hole's nearest covered pixel


def widened_camera(K: torch.Tensor, width: int, height: int, settings: HoleClosingSettings
                   ) -> tuple[torch.Tensor, int, int, tuple[int, int]]:
    """(K, width, height) of the keyframe's camera widened by the margin and scaled to the closing resolution, and
    the (column, row) offset of the keyframe's image in it."""
    r = settings.resolution
    pad_x, pad_y = round(settings.margin * width * r), round(settings.margin * height * r)
    wide = K.detach().clone().to(torch.float32)
    wide[:2] *= r
    wide[0, 2] += pad_x
    wide[1, 2] += pad_y
    return wide, round(width * r) + 2 * pad_x, round(height * r) + 2 * pad_y, (pad_x, pad_y)


def hole_surfels(render: RenderResult, K: torch.Tensor, photo: np.ndarray | None, offset: tuple[int, int],
                 settings: HoleClosingSettings) -> Surfels:
    """Camera-frame surfels for the holes of `render` (made with the widened K), coloured by `photo` (float [h, w,
    3] in [0, 1] at the closing resolution, placed at `offset`; None: the inpainted render everywhere). Empty when
    the render has no hole, or covers less than `min_covered` of the keyframe's own frame (a view the map barely
    reaches: extrapolating its few covered pixels over it would hang a sheet of guessed depth in front of other
    views). Holes farther than `reach` from a covered pixel stay open."""
    alpha = render.alpha.detach().cpu().numpy()
    hole = alpha < settings.max_alpha
    covered = ~hole & (render.depth.detach().cpu().numpy() > 0)
    device = render.rgb.device
    x0, y0 = offset
    frame = covered[y0:covered.shape[0] - y0, x0:covered.shape[1] - x0]
    if not hole.any() or frame.mean() < settings.min_covered:
        return Surfels.empty(device)
    reach = settings.reach * min(frame.shape)
    hole &= cv2.distanceTransform((~covered).astype(np.uint8), cv2.DIST_L2, 5) <= reach
    mask = (~covered).astype(np.uint8)
    depth = render.depth.detach().cpu().numpy()
    inverse = extrapolate_inverse_depth(np.where(covered, 1.0 / np.where(covered, depth, 1.0), 0.0), covered,
                                        settings.plane_radius)
    colours = render.rgb.detach().cpu().numpy() / np.maximum(alpha, 1e-6)[..., None]
    canvas = np.where(covered[..., None], np.clip(colours, 0, 1), 0.0)
    canvas = cv2.inpaint((canvas * 255 + 0.5).astype(np.uint8), mask, settings.inpaint_radius,
                         cv2.INPAINT_TELEA).astype(np.float32) / 255.0
    if photo is not None:
        h, w = photo.shape[:2]
        canvas[y0:y0 + h, x0:x0 + w] = photo
    # One pixel into the covered region too: the new surfels overlap the edge they continue (no seam of low alpha).
    keep = cv2.dilate(hole.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & (inverse > 0) & np.isfinite(
        inverse)
    rows, cols = np.nonzero(keep)
    if len(rows) == 0:
        return Surfels.empty(device)
    z = 1.0 / inverse[rows, cols]
    Kn = K.detach().cpu().numpy().astype(np.float64)
    x = (cols + 0.5 - Kn[0, 2]) / Kn[0, 0] * z
    y = (rows + 0.5 - Kn[1, 2]) / Kn[1, 1] * z
    means = np.stack([x, y, z], -1)
    sigma = SIGMA_PIXELS * z / Kn[0, 0]
    count = len(rows)
    quats = np.zeros((count, 4))
    quats[:, 0] = 1.0  # facing the camera (normal along its z axis)
    as_tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
    return Surfels(means=as_tensor(means), quats=as_tensor(quats), scales=as_tensor(np.stack([sigma, sigma], -1)),
                   opacities=torch.full((count,), settings.opacity, dtype=torch.float32, device=device),
                   colors=as_tensor(canvas[rows, cols]), keyframe_ids=torch.full((count,), -1, dtype=torch.int64,
                                                                                 device=device))


def extrapolate_inverse_depth(inverse: np.ndarray, covered: np.ndarray, radius: int) -> np.ndarray:
    """Inverse depth [H, W] everywhere: covered pixels keep theirs; every other pixel continues the plane (inverse
    depth affine in the pixel coordinates) fitted to the covered pixels within `radius` of its nearest covered
    pixel, clipped to the covered pixels' range. Where that window's pixels do not span a plane, the nearest
    pixel's value is held."""
    H, W = inverse.shape
    holes = (~covered).astype(np.uint8)
    _, labels = cv2.distanceTransformWithLabels(holes, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    sources = np.argwhere(holes == 0)  # label k (1-based) is the k-th covered pixel in raster order
    rows, cols = np.nonzero(holes)
    nearest = sources[labels[rows, cols] - 1]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    u, v = u / radius, v / radius  # window-sized units: well-conditioned moments
    q = np.where(covered, inverse, 0.0).astype(np.float64)
    w = covered.astype(np.float64)
    channels = [w, w * u, w * v, w * u * u, w * u * v, w * v * v, q, q * u, q * v]
    size = (2 * radius + 1, 2 * radius + 1)
    sums = np.stack([cv2.boxFilter(c, cv2.CV_64F, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
                     for c in channels], -1)[nearest[:, 0], nearest[:, 1]]
    n, su, sv, suu, suv, svv, sq, suq, svq = sums.T
    A = np.stack([np.stack([suu, suv, su], -1), np.stack([suv, svv, sv], -1), np.stack([su, sv, n], -1)], -2)
    b = np.stack([suq, svq, sq], -1)
    m = np.maximum(n, 1)
    spread = (suu / m - (su / m) ** 2) * (svv / m - (sv / m) ** 2) - (suv / m - su * sv / m ** 2) ** 2
    planar = (n >= 6) & (spread > 1e-3)
    coef = np.zeros_like(b)
    if planar.any():
        coef[planar] = np.linalg.solve(A[planar], b[planar][..., None])[..., 0]
    ur, vr = cols / radius, rows / radius
    plane = coef[:, 0] * ur + coef[:, 1] * vr + coef[:, 2]
    value = np.where(planar, plane, inverse[nearest[:, 0], nearest[:, 1]])
    low, high = np.percentile(inverse[covered], [1, 99])
    low, high = low / RANGE_MARGIN, high * RANGE_MARGIN
    out = inverse.astype(np.float32).copy()
    out[rows, cols] = np.clip(value, low, high)
    return out
