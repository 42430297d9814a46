"""The compiled kernels agree with the numpy reference, stage by stage and end to end."""

from __future__ import annotations

import numpy as np
import pytest
from scenes import Scene, pinhole, translation

from worker.depth import MultiViewDepthConfig, estimate_depth, mvs_cpu, reference
from worker.depth.sweep import inverse_depths, reference_stats, view_geometry

W, H, D, RADIUS = 64, 48, 48, 3
K = pinhole(W, H)
SCENE = Scene(plane_depth=2.0, boxes=[(np.array([-0.3, -0.2, 1.2]), np.array([0.2, 0.3, 1.5]))], texel=0.02)
POSES = [translation(-0.25), translation(0.2, 0.05), translation(0.0, -0.2)]


@pytest.fixture(scope="module")
def inputs():
    assert mvs_cpu.available(), mvs_cpu.load_error()
    grey = lambda p: SCENE.render(p, K, W, H)[0][..., 0].astype(np.float32) / 255.0  # noqa: E731
    ref = grey(translation(0.0))
    views = np.stack([grey(p) for p in POSES])
    geoms = [view_geometry(K, translation(0.0), p) for p in POSES]
    A, b = np.stack([g.A for g in geoms]), np.stack([g.b for g in geoms])
    ref_sum, ref_ssd = reference_stats(ref, RADIUS)
    return ref, ref_sum, ref_ssd, views, A, b, inverse_depths(1.0, 4.0, D)


def test_cost_volume(inputs):
    fast = mvs_cpu.cost_volume(*inputs, RADIUS, 1e-5, threads=2)
    slow = reference.cost_volume(*inputs, RADIUS, 1e-5)
    assert fast.shape == slow.shape == (len(POSES), D, H, W)
    assert np.mean((fast < 0) == (slow < 0)) > 0.999  # the same samples fall outside the views
    both = (fast >= 0) & (slow >= 0)
    assert both.mean() > 0.5
    close = np.abs(fast[both] - slow[both]) < 1e-3  # float32 sums in C++, float64 in numpy
    assert close.mean() > 0.999


def test_fuse_sgm_and_decision_terms(inputs):
    cost = reference.cost_volume(*inputs, RADIUS, 1e-5)
    fused_fast, min_fast = mvs_cpu.fuse_views(cost, 2, threads=2)
    fused_slow, min_slow = reference.fuse_views(cost, 2)
    np.testing.assert_allclose(fused_fast, fused_slow, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(min_fast, min_slow)

    for paths in (4, 8):
        total_fast = mvs_cpu.sgm(fused_slow, 0.03, 0.25, paths, threads=2)
        total_slow = reference.sgm(fused_slow, 0.03, 0.25, paths)
        np.testing.assert_allclose(total_fast, total_slow, rtol=1e-5, atol=1e-4)

    fast = mvs_cpu.decide_terms(total_slow, fused_slow, cost, min_slow, 0.1, 0.6, threads=2)
    slow = reference.decide_terms(total_slow, fused_slow, cost, min_slow, 0.1, 0.6)
    np.testing.assert_allclose(fast.index, slow.index, atol=1e-6)
    for name in ("interior", "support"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name))
    for name in ("uniqueness", "margin", "photometric"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), atol=1e-5)


def test_estimate_depth_backends_agree():
    image = SCENE.render(translation(0.0), K, W, H)[0]
    neighbours = [(SCENE.render(p, K, W, H)[0], p) for p in POSES]
    fast = estimate_depth(image, K, translation(0.0), neighbours, (1.0, 4.0), MultiViewDepthConfig(backend="cpu"))
    slow = estimate_depth(image, K, translation(0.0), neighbours, (1.0, 4.0),
                          MultiViewDepthConfig(backend="reference"))
    assert (fast.backend, slow.backend) == ("cpu", "reference")
    assert fast.coverage > 0.5
    assert np.mean(fast.mask == slow.mask) > 0.99
    both = fast.mask & slow.mask
    assert np.mean(np.abs(fast.depth[both] - slow.depth[both]) < 1e-3 * slow.depth[both]) > 0.99
