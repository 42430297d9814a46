"""A camera's turn from whole-image intensities, for frames whose corner tracks fail: walls of stripes (an aperture
problem for every point tracker), blur, faint texture.

The current image is aligned to a reference image (the last tracked frame) by the rotation of the current camera
about its own centre, its position given (the constant-velocity motion) and the scene taken as a fronto-parallel
plane at the map's median depth: a reference pixel x with ray r (z = 1) lands at pi(K R_delta (R d r + t)) in the
current image. Gauss-Newton on the rotation over an image pyramid (coarse to fine), Huber weights on the intensity
residuals (their scale from the median absolute residual), and the predicted turn as a prior of `prior_deg` per
axis: the directions the image does not constrain (vertical stripes fix yaw and roll, not pitch) stay at the
prediction instead of wandering. The fit reports what the image measured (the standard deviation of the turn along
each axis from the image alone), the overlap and the zero-normalised correlation of the aligned images, so that the
caller accepts only a good fit of an informative image (a blank wall measures nothing and is refused).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DirectSettings:
    """How the alignment runs and what it accepts."""

    levels: int = 4  # pyramid levels, the finest the image itself
    iterations: int = 12  # Gauss-Newton steps per level at most
    max_pixels: int = 6000  # reference pixels used per level (the strongest gradients, spread over the image)
    prior_deg: float = 2.0  # standard deviation of the predicted turn per axis, degrees
    min_overlap: float = 0.4  # share of the used reference pixels that land in the current image
    min_inliers: float = 0.6  # share of those whose residual is within 2.5 robust sigmas
    min_correlation: float = 0.75  # zero-normalised correlation of the aligned images, at least
    max_axis_sigma_deg: float = 0.25  # the best-measured direction must be known to this (image alone), degrees
    min_gradient: float = 2.0 / 255.0  # gradients weaker than this (intensity per pixel) carry no information
    min_information_ratio: float = 1e-3  # directions measured this much worse than the best are left to the prior
    max_correction_deg: float = 6.0  # a fit this far from the predicted turn left the basin of the alignment


@dataclass
class DirectFit:
    """An alignment: `rotation` takes reference-camera rays to current-camera rays (R, X_cur = R X_ref + t);
    `information` [3, 3] is what the image alone measured of the turn about the current camera's axes (radians^-2,
    zero along the directions it does not measure); `correlation` (over the pixels that agree), `overlap` and
    `residual` (RMS, 0-1 intensities) describe the fit at the finest level; `accepted` says whether it passed the
    settings' tests, `reason` why not."""

    rotation: np.ndarray
    translation: np.ndarray
    information: np.ndarray
    correlation: float
    overlap: float
    residual: float
    accepted: bool
    reason: str = ""

    def sigma_deg(self, axis: np.ndarray) -> float:
        """Standard deviation (degrees) of the turn about the unit `axis` (current camera) from the image alone."""
        info = float(axis @ self.information @ axis)
        return float(np.degrees(1.0 / np.sqrt(info))) if info > 0 else float("inf")

    @property
    def axis_sigma_deg(self) -> np.ndarray:
        """`sigma_deg` about the current camera's x (pitch), y (yaw) and z (roll) axes."""
        return np.array([self.sigma_deg(axis) for axis in np.eye(3)])

    @property
    def measured_axes(self) -> int:
        """How many independent directions of the turn the image pinned down to better than half a degree."""
        return int((np.linalg.eigvalsh(self.information) > np.radians(0.5) ** -2).sum())


def _pyramid(gray: np.ndarray, levels: int) -> list[np.ndarray]:
    """Float images (0-1), finest first, each lightly smoothed (the warp samples between pixels)."""
    image = cv2.GaussianBlur(gray.astype(np.float32) / 255.0, (3, 3), 0.8)
    out = [image]
    for _ in range(levels - 1):
        if min(out[-1].shape) < 16:
            break
        out.append(cv2.pyrDown(out[-1]))
    return out


def _gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=0.125),
            cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=0.125))


def _reference_pixels(image: np.ndarray, count: int, min_gradient: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres [N, 2] (project convention, +0.5) and intensities [N] of the strongest gradient of each cell of
    a grid (cells of 4x4, 2x2 or 1 pixel: the largest that still gives `count` cells), so that they spread over the
    image: the strongest `count` of them above `min_gradient`."""
    gx, gy = _gradients(image)
    magnitude = np.hypot(gx, gy)
    border = 2
    magnitude[:border], magnitude[-border:], magnitude[:, :border], magnitude[:, -border:] = 0, 0, 0, 0
    h, w = image.shape
    cell = next((size for size in (4, 2) if (h // size) * (w // size) >= count), 1)
    rows_c, cols_c = h // cell, w // cell
    blocks = magnitude[:rows_c * cell, :cols_c * cell].reshape(rows_c, cell, cols_c, cell).transpose(0, 2, 1, 3)
    blocks = blocks.reshape(rows_c, cols_c, cell * cell)
    best = blocks.argmax(axis=2)
    values = np.take_along_axis(blocks, best[..., None], axis=2)[..., 0]
    r0, c0 = np.nonzero(values > min_gradient)
    values, best = values[r0, c0], best[r0, c0]
    if len(values) > count:
        keep = np.argpartition(-values, count)[:count]
        r0, c0, best = r0[keep], c0[keep], best[keep]
    rows, cols = r0 * cell + best // cell, c0 * cell + best % cell
    uv = np.column_stack([cols + 0.5, rows + 0.5])
    return uv, image[rows, cols]


def _sample(images: list[np.ndarray], uv: np.ndarray) -> list[np.ndarray]:
    """Bilinear samples [N] of each image at pixels uv [N, 2] (project convention)."""
    mx = (uv[:, 0] - 0.5).astype(np.float32).reshape(1, -1)
    my = (uv[:, 1] - 0.5).astype(np.float32).reshape(1, -1)
    return [cv2.remap(im, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel() for im in images]


def _exp(omega: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(omega, np.float64).reshape(3, 1))[0]


def _log(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(R)[0].ravel()


class _Level:
    """One pyramid level: the reference pixels' rays and intensities and the current image with its gradients."""

    def __init__(self, reference: np.ndarray, current: np.ndarray, K: np.ndarray, settings: DirectSettings) -> None:
        self.K = K
        uv, self.intensity = _reference_pixels(reference, settings.max_pixels, settings.min_gradient)
        self.rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1],
                                     np.ones(len(uv))])
        gx, gy = _gradients(current)
        self.images = [current, gx, gy]
        self.size = current.shape

    def residuals(self, R: np.ndarray, t: np.ndarray, depth: float):
        """Residuals, Jacobian rows [N, 6] (d residual / d turn of the current camera, then / d t) and the in-view
        mask."""
        K = self.K
        Y = depth * self.rays @ R.T + t
        z = Y[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        u = K[0, 0] * Y[:, 0] / zs + K[0, 2]
        v = K[1, 1] * Y[:, 1] / zs + K[1, 2]
        h, w = self.size
        inside = front & (u >= 1.0) & (u <= w - 1.0) & (v >= 1.0) & (v <= h - 1.0)
        value, gx, gy = _sample(self.images, np.column_stack([u, v]))
        r = value - self.intensity
        # d pixel / d Y, then d Y / d omega = -[Y]_x for Y -> exp(omega) Y
        du = np.column_stack([K[0, 0] / zs, np.zeros_like(zs), -K[0, 0] * Y[:, 0] / zs ** 2])
        dv = np.column_stack([np.zeros_like(zs), K[1, 1] / zs, -K[1, 1] * Y[:, 1] / zs ** 2])
        dI = gx[:, None] * du + gy[:, None] * dv  # d intensity / d Y  [N, 3]
        J = np.cross(Y, dI)  # d intensity / d omega = -dI^T [Y]_x
        return r, np.concatenate([J, dI], axis=1), inside


def _measured(H: np.ndarray, g: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations (H, g) kept to the directions the image measures: eigen-directions of H whose
    information is below `ratio` of the strongest are dropped (there, blur and sampling, not the scene, decide the
    minimum; the prior holds them)."""
    values, vectors = np.linalg.eigh(H)
    kept = vectors[:, values >= ratio * max(float(values[-1]), 1e-300)]
    return kept @ (kept.T @ H @ kept) @ kept.T, kept @ (kept.T @ g)


def _huber_weights(r: np.ndarray) -> tuple[np.ndarray, float]:
    scale = max(1.4826 * float(np.median(np.abs(r))), 1.0 / 255.0)
    k = 1.345 * scale
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12)), scale


def align_rotation(reference: np.ndarray, current: np.ndarray, K: np.ndarray, prior_rotation: np.ndarray,
                   translation: np.ndarray | None = None, depth: float = 1.0, translation_sigma: float = 0.0,
                   settings: DirectSettings | None = None) -> DirectFit:
    """Align `current` to `reference` (uint8 grey images of one size) by the current camera's turn: `prior_rotation`
    [3, 3] the predicted R (X_cur = R X_ref + t), `translation` t [3] (current-camera frame; zero: a turn in place)
    and `depth` the scene plane's distance in the reference camera, in the units of t. With `translation_sigma` > 0
    the camera centre moves too, held to the predicted one by that standard deviation per axis (units of t); else it
    stays where predicted. See the module docstring."""
    s = settings or DirectSettings()
    t0 = np.zeros(3) if translation is None else np.asarray(translation, np.float64)
    R, t = np.asarray(prior_rotation, np.float64).copy(), t0.copy()
    centre0 = -R.T @ t0
    moves = translation_sigma > 0
    dof = 6 if moves else 3
    prior_info = np.diag(np.r_[np.full(3, np.radians(s.prior_deg) ** -2.0),
                               np.full(3, translation_sigma ** -2.0 if moves else 0.0)])[:dof, :dof]
    refs, curs = _pyramid(reference, s.levels), _pyramid(current, s.levels)
    levels = min(len(refs), len(curs))
    last: _Level | None = None
    for level in range(levels - 1, -1, -1):
        scale = 0.5 ** level
        K_level = np.diag([scale, scale, 1.0]) @ K
        data = _Level(refs[level], curs[level], K_level, s)
        if len(data.intensity) < 20:
            continue
        for _ in range(s.iterations):
            r, J, inside = data.residuals(R, t, depth)
            if inside.sum() < 20:
                break
            w, sigma = _huber_weights(r[inside])
            Ji, ri = J[inside, :dof], r[inside]
            H, g = _measured((Ji * w[:, None]).T @ Ji / sigma ** 2, (Ji * w[:, None]).T @ ri / sigma ** 2,
                             s.min_information_ratio)
            # the priors' residuals: the turn about the current camera's axes, the centre moved (a step dt moves
            # the centre by -R^T dt, so its prior pulls dt towards R (centre - predicted centre))
            error = _log(R @ prior_rotation.T)
            g[:3] += prior_info[:3, :3] @ error
            if moves:
                g[3:] -= prior_info[3:, 3:] @ (R @ (-R.T @ t - centre0))
            step = np.linalg.solve(H + prior_info, -g)
            turn = _exp(step[:3])
            R, t = turn @ R, turn @ t + (step[3:] if moves else 0.0)
            if np.linalg.norm(step) < 1e-5:
                break
        last = data
    if last is None:
        return DirectFit(R, t, np.zeros((3, 3)), 0.0, 0.0, float("inf"), False, "no image gradient")
    data = last
    r, J, inside = data.residuals(R, t, depth)
    overlap = float(inside.mean())
    if inside.sum() >= 20:
        w, sigma = _huber_weights(r[inside])
        H_image = _measured((J[inside, :3] * w[:, None]).T @ J[inside, :3] / sigma ** 2, np.zeros(3),
                            s.min_information_ratio)[0]
        agree = np.abs(r[inside]) <= 2.5 * sigma  # parallax and occlusions are outliers, not a poor fit
        inliers = float(agree.mean())
        a, b = data.intensity[inside][agree], (r[inside] + data.intensity[inside])[agree]
        a, b = a - a.mean(), b - b.mean()
        denominator = float(np.sqrt((a * a).sum() * (b * b).sum()))
        correlation = float((a * b).sum() / denominator) if denominator > 1e-12 else 0.0
        residual = float(np.sqrt(np.mean(r[inside] ** 2)))
    else:
        correlation, residual, inliers, H_image = 0.0, float("inf"), 0.0, np.zeros((3, 3))
    # Pixels are not independent (neighbours share noise and blur): the image's information is counted per 8x8 cell.
    fit = DirectFit(R, t, H_image / 64.0, correlation, overlap, residual, False)
    best_sigma = float(np.degrees(1.0 / np.sqrt(max(float(np.linalg.eigvalsh(fit.information)[-1]), 1e-300))))
    if not np.all(np.isfinite(R)):
        fit.reason = "non-finite rotation"
    elif (correction := float(np.degrees(np.linalg.norm(_log(R @ np.asarray(prior_rotation).T))))) > \
            s.max_correction_deg:
        fit.reason = f"{correction:.1f} deg from the predicted turn (> {s.max_correction_deg})"
    elif overlap < s.min_overlap:
        fit.reason = f"overlap {overlap:.2f} < {s.min_overlap}"
    elif inliers < s.min_inliers:
        fit.reason = f"{inliers:.2f} of the pixels agree < {s.min_inliers}"
    elif best_sigma > s.max_axis_sigma_deg:
        fit.reason = f"the image measures no turn (best direction +-{best_sigma:.2f} deg)"
    elif correlation < s.min_correlation:
        fit.reason = f"correlation {correlation:.2f} < {s.min_correlation}"
    else:
        fit.accepted = True
    return fit
