"""The compiled dense-alignment kernels (worker.tracking.dense_native) against their numpy reference
(worker.tracking.dense_reference, the oracle): a level's points, normals and depth downsampling, and each
Gauss-Newton iteration's normal equations, on real ICL frames (tests/data/icl_mini) and on constructed geometry;
the odometry's trajectory with either backend; the fallback to the reference when no compiler is available."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from native_fallback import run_without_compiler

from worker.data import open_source
from worker.tracking import dense_native, dense_reference
from worker.tracking.dense_alignment import (
    MIN_POINTS,
    AlignmentSettings,
    PyramidLevel,
    align,
    build_pyramid,
    solve_level,
)
from worker.tracking.dense_alignment import _se3_exp as se3_exp
from worker.tracking.rgbd_odometry import RgbdOdometry, grey_of

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "icl_mini"
SETTINGS = AlignmentSettings()

pytestmark = pytest.mark.skipif(not dense_native.available(), reason=f"no kernels: {dense_native.load_error()}")


@pytest.fixture(scope="module")
def icl():
    src = open_source(str(DATA), use_gt_depth=True, use_gt_poses=False)
    return list(src), src.intrinsics.matrix().numpy().astype(np.float64)


def _pyramids(frames, K, a: int, b: int) -> tuple[list[PyramidLevel], list[PyramidLevel]]:
    return tuple(build_pyramid(grey_of(frames[i].image), frames[i].depth, K, 3, backend="reference") for i in (a, b))


def _constructed(width: int = 96, height: int = 72) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured slanted plane with a box standing out of it: (grey, depth, K)."""
    K = np.array([[80.0, 0.0, width / 2], [0.0, 80.0, height / 2], [0.0, 0.0, 1.0]])
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x, y = (jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1]
    depth = 2.0 / (1.0 + 0.3 * x + 0.1 * y)  # the plane 0.3 X + 0.1 Y + Z = 2
    box = (np.abs(x - 0.15) < 0.15) & (np.abs(y + 0.1) < 0.12)
    depth = np.where(box, 1.6, depth).astype(np.float32)
    grey = 0.5 + 0.2 * np.sin(9 * x * depth) * np.cos(7 * y * depth) + 0.1 * box
    return grey.astype(np.float32), depth, K


def _assert_systems_equal(ref: dense_reference.TermSystem, fast: dense_reference.TermSystem,
                          rtol: float) -> None:
    assert fast.used == ref.used and fast.found == ref.found
    if ref.used == 0:
        assert not fast.H.any() and not fast.g.any()
        return
    assert fast.scale == pytest.approx(ref.scale, rel=rtol)
    np.testing.assert_allclose(fast.H, ref.H, rtol=0, atol=rtol * np.abs(ref.H).max())
    # g against its natural size sqrt(|H| n) (whitened residuals are O(1)): at an exact fit r is rounding noise
    natural = max(np.abs(ref.g).max(), np.sqrt(np.abs(ref.H).max() * ref.used))
    np.testing.assert_allclose(fast.g, ref.g, rtol=0, atol=rtol * natural)
    np.testing.assert_array_equal(fast.H, fast.H.T)


def _compare_terms(ref_level: PyramidLevel, cur: PyramidLevel, T: np.ndarray) -> None:
    s = ref_level.samples(SETTINGS.max_points, SETTINGS.min_gradient)
    image = (cur.grey, cur.grad_x, cur.grad_y)
    photometric = [m.photometric_system(s.photometric_points, s.intensity, T, cur.K, *image,
                                        SETTINGS.photometric_floor, 1.0, MIN_POINTS)
                   for m in (dense_reference, dense_native)]
    # float32 images are interpolated in double by the kernel, in float by OpenCV: 1e-5 of the largest entry
    _assert_systems_equal(*photometric, rtol=1e-5)
    geometric = [m.geometric_system(s.geometric_points, T, cur.K, cur.points, cur.normals, SETTINGS.max_association,
                                    SETTINGS.geometric_floor, 1.0, MIN_POINTS) for m in (dense_reference, dense_native)]
    _assert_systems_equal(*geometric, rtol=1e-9)


def test_level_kernels_equal_the_reference_on_a_real_frame(icl) -> None:
    frames, K = icl
    depth = np.asarray(frames[5].depth, np.float32)
    points = dense_reference.points(depth, K)
    np.testing.assert_array_equal(dense_native.points(depth, K), points)
    normals = dense_native.normals(points, 0.05)
    np.testing.assert_allclose(normals, dense_reference.normals(points, 0.05), atol=1e-6)
    assert (np.abs(normals).sum(-1) > 0).mean() > 0.5  # most pixels have a normal
    np.testing.assert_array_equal(dense_native.downsample_depth(depth, 0.05),
                                  dense_reference.downsample_depth(depth, 0.05))


def test_normal_equations_equal_the_reference_on_real_frames(icl) -> None:
    frames, K = icl
    reference, current = _pyramids(frames, K, 4, 6)
    truth = np.linalg.inv(frames[6].gt_pose) @ frames[4].gt_pose
    off = se3_exp(np.array([0.01, -0.02, 0.005, 0.03, 0.01, -0.02])) @ truth
    for level in range(3):
        for T in (np.eye(4), truth, off):
            _compare_terms(reference[level], current[level], T)


def test_normal_equations_equal_the_reference_on_constructed_geometry() -> None:
    grey, depth, K = _constructed()
    level = build_pyramid(grey, depth, K, 1, backend="reference")[0]
    # the plane's normal is known: (0.3, 0.1, 1) normalised, facing the camera
    plane = np.array([0.3, 0.1, 1.0]) / np.linalg.norm([0.3, 0.1, 1.0])
    n = dense_native.normals(level.points, 0.05)
    assert np.abs(n[5, 5] + plane).max() < 1e-4
    for delta in ([0, 0, 0, 0, 0, 0], [0.02, -0.01, 0.01, 0.05, -0.03, 0.02], [0, 0, 0.3, 0, 0, 0]):
        _compare_terms(level, level, se3_exp(np.array(delta, float)))
    # a pose that moves every point out of view leaves too few residuals: both report nothing used
    _compare_terms(level, level, se3_exp(np.array([0, 0, 0, 50.0, 0, 0])))
    # at the true pose of an image with itself every residual vanishes
    s = level.samples(SETTINGS.max_points, SETTINGS.min_gradient)
    exact = dense_native.geometric_system(s.geometric_points, np.eye(4), K, level.points, level.normals, 0.08,
                                          SETTINGS.geometric_floor, 1.0, MIN_POINTS)
    assert exact.used > 1000 and np.abs(exact.g).max() < 1e-9


def _solve_both(ref_level: PyramidLevel, cur: PyramidLevel, T: np.ndarray, iterations: int):
    """(T, state) from the compiled level loop and from the Python loop over the compiled per-iteration kernels."""
    s = SETTINGS
    samples = ref_level.samples(s.max_points, s.min_gradient)
    python_state, native_state = np.array([0.0, 0, 0, 0, 1]), np.array([0.0, 0, 0, 0, 1])
    python_T = solve_level(dense_native, samples, cur, T.copy(), s, iterations, python_state)
    native_T = T.copy()
    terms = (s.photometric_floor, s.photometric_weight, s.max_association, s.geometric_floor, s.geometric_weight)
    level = (samples.photometric_points, samples.intensity, samples.geometric_points, samples.depth, cur.K, cur.grey,
             cur.grad_x, cur.grad_y, cur.points, cur.normals, iterations)
    dense_native.align_levels([level], terms, MIN_POINTS, s.convergence, native_T, native_state)
    return (python_T, python_state), (native_T, native_state)


def test_compiled_level_loop_equals_the_python_loop(icl) -> None:
    frames, K = icl
    reference, current = _pyramids(frames, K, 4, 6)
    for level, iterations in ((2, 10), (0, 3)):
        (python_T, python_state), (native_T, native_state) = _solve_both(reference[level], current[level], np.eye(4),
                                                                         iterations)
        assert python_state[4] == 1 and python_state[3] > 1000
        assert np.abs(python_T[:3, 3]).max() > 0.01  # it moved towards the ~13 cm between the frames
        np.testing.assert_allclose(native_T, python_T, atol=1e-10)
        np.testing.assert_allclose(native_state, python_state, rtol=1e-9)
    # a start that sees nothing of the current frame is ill-posed in both
    far = se3_exp(np.array([0, 0, 0, 80.0, 0, 0]))
    (python_T, python_state), (native_T, native_state) = _solve_both(reference[1], current[1], far, 5)
    assert python_state[4] == 0 and native_state[4] == 0
    np.testing.assert_array_equal(native_T, far)


def test_alignment_recovers_a_known_motion_with_either_backend() -> None:
    grey, depth, K = _constructed(160, 120)
    pyramid = build_pyramid(grey, depth, K, 3)
    true_T = se3_exp(np.array([0.01, -0.015, 0.005, 0.02, 0.01, -0.03]))
    results = [align(pyramid, pyramid, true_T, AlignmentSettings(backend=b)) for b in ("reference", "native")]
    for result in results:
        assert result.ok and np.abs(result.T - np.eye(4)).max() < 1e-4  # an image against itself: identity
    np.testing.assert_allclose(results[1].T, results[0].T, atol=1e-7)


def test_odometry_trajectory_equals_the_reference(icl) -> None:
    frames, _ = icl
    intrinsics = open_source(str(DATA), use_gt_depth=True).intrinsics
    trajectories = []
    for backend in ("reference", "native"):
        odometry = RgbdOdometry()
        odometry.settings.backend = backend
        results = [odometry.track(f, intrinsics) for f in frames[:24]]
        assert all(r.tracked for r in results)
        trajectories.append(np.stack([r.pose for r in results]))
    moved = np.linalg.norm(trajectories[0][-1, :3, 3] - trajectories[0][0, :3, 3])
    assert moved > 0.3
    np.testing.assert_allclose(trajectories[1], trajectories[0], atol=1e-6)


def test_tracking_falls_back_to_the_references_without_a_compiler(tmp_path) -> None:
    """Dense alignment and bundle adjustment (worker.tracking.schur_native) both run their numpy references."""
    script = (
        "import logging, numpy as np\n"
        "logging.basicConfig(level=logging.WARNING)\n"
        "from worker.data import open_source\n"
        "from worker.tracking import dense_native\n"
        "from worker.tracking.dense_alignment import AlignmentSettings, kernels\n"
        "from worker.tracking.rgbd_odometry import RgbdOdometry\n"
        "src = open_source('tests/data/icl_mini', use_gt_depth=True, max_frames=4)\n"
        "odometry = RgbdOdometry()\n"
        "results = [odometry.track(f, src.intrinsics) for f in src]\n"
        "assert all(r.tracked for r in results) and not dense_native.available()\n"
        "assert np.linalg.norm(results[-1].pose[:3, 3]) > 0.05, results[-1].pose\n"
        "try:\n"
        "    kernels('native')\n"
        "except RuntimeError as err:\n"
        "    print('REFUSED', err)\n"
        "from worker.tracking import schur_native\n"
        "from worker.tracking.bundle_adjustment import Observations, bundle_adjust\n"
        "K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])\n"
        "X = np.random.default_rng(0).uniform([-1, -1, 3], [1, 1, 5], (60, 3))\n"
        "poses = np.stack([np.eye(4)] * 3); poses[1, 0, 3], poses[2, 0, 3] = 0.2, 0.4\n"
        "uv = [(X - p[:3, 3]) @ K.T for p in poses]; uv = np.concatenate([u[:, :2] / u[:, 2:] for u in uv])\n"
        "obs = Observations(np.repeat(np.arange(3), 60), np.tile(np.arange(60), 3), uv + 0.3, np.ones(180))\n"
        "_, _, ran = bundle_adjust(poses, np.array([True, False, False]), X, obs, K)\n"
        "assert ran and not schur_native.available()\n"
        "print('FELL BACK')\n"
    )
    result = run_without_compiler(script, tmp_path)
    assert "FELL BACK" in result.stdout and "REFUSED compiled dense-alignment kernels unavailable" in result.stdout
    assert "using the numpy reference" in result.stderr
