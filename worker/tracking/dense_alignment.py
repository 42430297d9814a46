"""Dense RGB-D frame alignment: the rigid motion that maps a reference RGB-D frame onto the current one.

Coarse-to-fine Gauss-Newton over an image pyramid on two kinds of residual, each with its own robust (Huber) scale
estimated from the residuals themselves:
- photometric: intensity of a reference pixel minus the current image sampled where its 3D point lands (minus the
  median difference, which absorbs a global brightness change such as auto-exposure);
- geometric: point-to-plane distance between the moved reference point and the current frame's surface at the
  pixel it projects to (projective association).
The update is a left perturbation exp(delta) T of T_cur_ref (p_cur = T p_ref). Pixel centres are at +0.5 (see
worker.geometry.camera); every threshold is relative to depth, so nothing assumes metres.

The per-pixel work (a level's points and normals, each iteration's normal equations) and the Gauss-Newton loop
over all levels run in compiled kernels (`worker.tracking.dense_native`, one call per alignment, without the GIL)
or, where they cannot be built or `backend="reference"`, in their numpy twins (`worker.tracking.dense_reference`
and `solve_level`, the test oracles); this module keeps the pyramid and the choice of reference pixels.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from types import ModuleType
from typing import Literal

import cv2
import numpy as np

from . import dense_native, dense_reference

log = logging.getLogger(__name__)

MIN_POINTS = 60  # per pyramid level; fewer leave six degrees of freedom poorly constrained
Backend = Literal["auto", "native", "reference"]
_warned = False


def kernels(backend: Backend = "auto") -> ModuleType:
    """The kernel module for `backend`: "auto" is the compiled one when it builds, else the numpy reference
    (saying so once per process); "native" raises when it cannot be built."""
    global _warned
    if backend == "reference":
        return dense_reference
    if dense_native.available():
        return dense_native
    if backend == "native":
        raise RuntimeError(f"compiled dense-alignment kernels unavailable: {dense_native.load_error()}")
    if not _warned:
        _warned = True
        log.warning("compiled dense-alignment kernels unavailable (%s); using the numpy reference",
                    dense_native.load_error())
    return dense_reference


@dataclass
class PyramidLevel:
    """One resolution of an RGB-D frame: intensity, its gradients, camera-frame points and normals, K."""

    grey: np.ndarray  # float32 [h, w] in [0, 1]
    grad_x: np.ndarray
    grad_y: np.ndarray
    points: np.ndarray  # float32 [h, w, 3], z = 0 where depth is unknown
    normals: np.ndarray  # float32 [h, w, 3], 0 where undefined
    K: np.ndarray  # float64 [3, 3]
    # the reference pixels chosen per (max_points, min_gradient): a reference frame is aligned to many frames
    _samples: dict[tuple[int, float], ReferenceSamples] = field(default_factory=dict, repr=False, compare=False)

    def samples(self, max_points: int, min_gradient: float) -> ReferenceSamples:
        """This level's reference pixels for the two terms (chosen once, see `_select`)."""
        key = (max_points, min_gradient)
        if key not in self._samples:
            photo, geo = _select(self, max_points, min_gradient)
            flat = self.points.reshape(-1, 3)
            z = flat[geo if geo.size else photo, 2]
            self._samples[key] = ReferenceSamples(flat[photo].astype(np.float64),
                                                  self.grey.ravel()[photo].astype(np.float64),
                                                  flat[geo].astype(np.float64),
                                                  float(np.median(z)) if z.size else 1.0)
        return self._samples[key]


@dataclass
class ReferenceSamples:
    """The reference pixels of one level: points and intensities for the photometric term, points for the
    geometric one (float64)."""

    photometric_points: np.ndarray  # [n, 3]
    intensity: np.ndarray  # [n]
    geometric_points: np.ndarray  # [m, 3]
    depth: float  # their median depth: the unit of translation in the convergence test


@dataclass
class AlignmentResult:
    """T_cur_ref (4x4 float64), the fraction of reference points that found the current surface within the
    geometric threshold (overlap), the robust residual scales and whether the solve stayed well posed."""

    T: np.ndarray
    overlap: float
    photometric_rms: float
    geometric_rms: float
    ok: bool
    points_used: int


def fit_at(reference: list[PyramidLevel], current: list[PyramidLevel], T: np.ndarray,
           settings: AlignmentSettings | None = None) -> AlignmentResult:
    """How well T_cur_ref fits as it stands (no step taken), on the finest level: the overlap and robust residual
    scales `align` reports for the pose it settles on."""
    s = settings or AlignmentSettings()
    ops = kernels(s.backend)
    T = np.array(T, np.float64, order="C")
    samples = reference[0].samples(s.max_points, s.min_gradient)
    cur = current[0]
    photo = ops.photometric_system(samples.photometric_points, samples.intensity, T, cur.K, cur.grey, cur.grad_x,
                                   cur.grad_y, s.photometric_floor, s.photometric_weight, MIN_POINTS)
    geo = ops.geometric_system(samples.geometric_points, T, cur.K, cur.points, cur.normals, s.max_association,
                               s.geometric_floor, s.geometric_weight, MIN_POINTS)
    used = photo.used + geo.used
    return AlignmentResult(T, geo.found / max(1, samples.geometric_points.shape[0]), float(photo.scale),
                           float(geo.scale), used >= MIN_POINTS, int(used))


def fits_clearly_better(candidate: AlignmentResult, incumbent: AlignmentResult, ratio: float = 0.9) -> bool:
    """Whether `candidate` (the same frame aligned to the same reference from another guess) fits clearly better:
    one robust residual scale (intensity or depth) at most `ratio` times the incumbent's, the other at most
    1/`ratio` times it, and an overlap not smaller by more than 0.05."""
    if not candidate.ok or candidate.overlap < incumbent.overlap - 0.05:
        return False
    photometric = candidate.photometric_rms / max(incumbent.photometric_rms, 1e-12)
    geometric = candidate.geometric_rms / max(incumbent.geometric_rms, 1e-12)
    return min(photometric, geometric) <= ratio and max(photometric, geometric) <= 1.0 / ratio


def build_pyramid(grey: np.ndarray, depth: np.ndarray, K: np.ndarray, levels: int,
                  edge_ratio: float = 0.05, backend: Backend = "auto") -> list[PyramidLevel]:
    """Levels from full resolution (index 0) down by 2 each; `grey` float32 [0, 1], `depth` float32 (0 = none)."""
    ops = kernels(backend)
    out: list[PyramidLevel] = []
    K = np.asarray(K, np.float64)
    depth = np.ascontiguousarray(depth, np.float32)
    for level in range(levels):
        if level > 0:
            grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
            depth = ops.downsample_depth(depth, edge_ratio)
            K = K.copy()
            K[:2] *= 0.5
        gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        pts = ops.points(depth, K)
        out.append(PyramidLevel(grey, gx, gy, pts, ops.normals(pts, edge_ratio), K))
    return out


def _se3_exp(delta: np.ndarray) -> np.ndarray:
    omega, v = delta[:3], delta[3:]
    theta = float(np.linalg.norm(omega))
    W = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    if theta < 1e-10:
        R, V = np.eye(3) + W, np.eye(3) + 0.5 * W
    else:
        a, b = np.sin(theta) / theta, (1 - np.cos(theta)) / theta**2
        c = (1 - a) / theta**2
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + c * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def _select(level: PyramidLevel, max_points: int, min_gradient: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of reference pixels for the photometric term (textured, with depth) and the geometric term
    (with a normal), each at most `max_points`, spread evenly over the image."""
    z = level.points[..., 2].ravel()
    grad = np.hypot(level.grad_x, level.grad_y).ravel()
    photo = np.flatnonzero((z > 0) & (grad > min_gradient))
    geo = np.flatnonzero(np.abs(level.normals[..., 2]).ravel() > 0)
    if photo.size > max_points:
        photo = photo[np.argsort(-grad[photo], kind="stable")[: 2 * max_points]]
        photo = np.sort(photo)[:: max(1, photo.size // max_points)]
    if geo.size > max_points:
        geo = geo[:: int(np.ceil(geo.size / max_points))]
    return photo, geo


@dataclass
class AlignmentSettings:
    """Iterations per level (index 0 = full resolution), points per term, the weight of the photometric term
    relative to the geometric one (both whitened by their robust scales), the association threshold (relative to
    depth) and which kernels run the per-pixel work (see `kernels`)."""

    iterations: tuple[int, ...] = (10, 8, 6)
    max_points: int = 5000
    min_gradient: float = 0.02
    photometric_weight: float = 1.0
    geometric_weight: float = 1.0
    max_association: float = 0.08
    photometric_floor: float = 0.004
    geometric_floor: float = 0.0005
    convergence: float = 5e-5  # a level stops once an update moves less: |(omega, v / median depth)|
    backend: Backend = "auto"


def solve_level(ops: ModuleType, samples: ReferenceSamples, cur: PyramidLevel, T: np.ndarray,
                s: AlignmentSettings, iterations: int, state: np.ndarray) -> np.ndarray:
    """Gauss-Newton on one level with the per-iteration kernels of `ops`; returns T, updates state = (overlap,
    photometric scale, geometric scale, points used, ok) in place. `dense_native.align_levels` runs this loop
    compiled."""
    for _ in range(iterations):
        photo = ops.photometric_system(samples.photometric_points, samples.intensity, T, cur.K, cur.grey,
                                       cur.grad_x, cur.grad_y, s.photometric_floor, s.photometric_weight, MIN_POINTS)
        geo = ops.geometric_system(samples.geometric_points, T, cur.K, cur.points, cur.normals,
                                   s.max_association, s.geometric_floor, s.geometric_weight, MIN_POINTS)
        state[0] = geo.found / max(1, samples.geometric_points.shape[0])
        state[1] = photo.scale if photo.used else state[1]
        state[2] = geo.scale if geo.used else state[2]
        count = photo.used + geo.used
        if count < MIN_POINTS:
            state[4] = 0.0
            break
        H = photo.H + geo.H
        H += 1e-9 * np.trace(H) * np.eye(6)
        try:
            delta = -np.linalg.solve(H, photo.g + geo.g)
        except np.linalg.LinAlgError:
            state[4] = 0.0
            break
        if not np.all(np.isfinite(delta)):
            state[4] = 0.0
            break
        T = _se3_exp(delta) @ T
        state[3] = count
        if np.hypot(np.linalg.norm(delta[:3]), np.linalg.norm(delta[3:]) / samples.depth) < s.convergence:
            break
    return T


def align(reference: list[PyramidLevel], current: list[PyramidLevel], T_init: np.ndarray,
          settings: AlignmentSettings | None = None) -> AlignmentResult:
    """T_cur_ref refined from `T_init` by coarse-to-fine Gauss-Newton (see the module docstring)."""
    s = settings or AlignmentSettings()
    ops = kernels(s.backend)
    T = np.array(T_init, np.float64, order="C")
    levels = min(len(reference), len(current), len(s.iterations))
    state = np.array([0.0, 0.0, 0.0, 0.0, 1.0])  # overlap, photometric scale, geometric scale, points used, ok
    if ops is dense_native:  # every level in one compiled call: one GIL release, not two per iteration
        data = []
        for ref, cur, iterations in zip(reference[:levels], current[:levels], s.iterations, strict=False):
            samples = ref.samples(s.max_points, s.min_gradient)
            data.append((samples.photometric_points, samples.intensity, samples.geometric_points, samples.depth,
                         cur.K, cur.grey, cur.grad_x, cur.grad_y, cur.points, cur.normals, iterations))
        terms = (s.photometric_floor, s.photometric_weight, s.max_association, s.geometric_floor, s.geometric_weight)
        dense_native.align_levels(data, terms, MIN_POINTS, s.convergence, T, state)
    else:
        for level in reversed(range(levels)):
            samples = reference[level].samples(s.max_points, s.min_gradient)
            T = solve_level(ops, samples, current[level], T, s, s.iterations[level], state)
            if not state[4]:
                break
    ok = bool(state[4]) and bool(np.all(np.isfinite(T)))
    return AlignmentResult(T, float(state[0]), float(state[1]), float(state[2]), ok, int(state[3]))
