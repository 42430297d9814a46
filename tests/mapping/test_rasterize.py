"""The rasterizer's maths on analytic scenes, against an independent float64 oracle, and its gradients.

Every behaviour is checked for both CPU backends (the pure-torch reference and the compiled path).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from raster_oracle import render_oracle

from worker.mapping import RenderResult, Surfels, rasterize

W, H = 64, 48
BACKENDS = ["reference", "cpu"]


def camera(dtype=torch.float64) -> torch.Tensor:
    return torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]], dtype=dtype)


def surfels_of(means, quats, scales, opacities, colors, dtype=torch.float64) -> Surfels:
    t = [torch.as_tensor(a, dtype=dtype) for a in (means, quats, scales, opacities, colors)]
    return Surfels(*t, keyframe_ids=torch.zeros(t[0].shape[0], dtype=torch.int64))


def random_scene(n: int, seed: int, dtype=torch.float64, scale_range=(0.03, 0.12), opacity_range=(0.05, 0.95),
                 extent=(1.5, 1.1)) -> Surfels:
    """n randomly oriented surfels 2-4 m in front of the identity camera, spread over +-extent metres."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = scale_range
    (olo, ohi), (ex, ey) = opacity_range, extent
    return surfels_of(
        torch.stack([(torch.rand(n, generator=g) * 2 - 1) * ex, (torch.rand(n, generator=g) * 2 - 1) * ey,
                     torch.rand(n, generator=g) * 2 + 2.0], -1),
        torch.randn(n, 4, generator=g),
        torch.rand(n, 2, generator=g) * (hi - lo) + lo,
        torch.rand(n, generator=g) * (ohi - olo) + olo,
        torch.rand(n, 3, generator=g),
        dtype,
    )


def look_from(yaw: float, t=(0.05, -0.03, 0.1), dtype=torch.float64) -> torch.Tensor:
    """A world->camera matrix with a small rotation about y and a translation."""
    c, s = math.cos(yaw), math.sin(yaw)
    V = torch.eye(4, dtype=dtype)
    V[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=dtype)
    V[:3, 3] = torch.tensor(t, dtype=dtype)
    return V


@pytest.fixture
def single_thread():
    """Finite-difference checks make hundreds of tiny renders: one thread avoids pool wake-ups on a busy machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def fronto_parallel(centre_xyz, scale, opacity, color=(1.0, 0.5, 0.25)) -> Surfels:
    return surfels_of([centre_xyz], [[1.0, 0, 0, 0]], [[scale, scale]], [opacity], [color])


@pytest.mark.parametrize("backend", BACKENDS)
def test_peak_alpha_equals_opacity_at_centre(backend):
    # surfel centred on pixel (20, 10)'s centre: x = 20.5, y = 10.5
    z = 2.0
    X, Y = (20.5 - 32) * z / 50, (10.5 - 24) * z / 50
    out = rasterize(fronto_parallel([X, Y, z], 0.2, 0.7), torch.eye(4, dtype=torch.float64), camera(), W, H,
                    backend=backend)
    assert isinstance(out, RenderResult)
    assert out.alpha[10, 20].item() == pytest.approx(0.7, abs=1e-6)
    assert out.alpha.max().item() == pytest.approx(0.7, abs=1e-6)
    assert torch.allclose(out.rgb[10, 20], 0.7 * torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64))
    assert out.depth[10, 20].item() == pytest.approx(z, abs=1e-9)
    # the normal of a fronto-parallel surfel faces the camera: -z, weighted by alpha
    assert torch.allclose(out.normals[10, 20], torch.tensor([0, 0, -0.7], dtype=torch.float64), atol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_falloff_at_known_offsets(backend):
    z, s, o = 2.0, 0.2, 0.9  # sigma in pixels = f s / z = 5 px, wide enough that the low-pass filter is inactive
    X, Y = (30.5 - 32) * z / 50, (20.5 - 24) * z / 50
    out = rasterize(fronto_parallel([X, Y, z], s, o), torch.eye(4, dtype=torch.float64), camera(), W, H,
                    backend=backend)
    sigma_px = 50 * s / z
    for dx, dy in [(1, 0), (3, 0), (0, 4), (5, 5), (-7, 2), (0, -9)]:
        r2 = dx * dx + dy * dy
        expected = o * math.exp(-r2 / (2 * sigma_px**2))
        got = out.alpha[20 + dy, 30 + dx].item()
        if expected >= 1 / 255:
            assert got == pytest.approx(expected, rel=1e-6), (dx, dy)
        else:
            assert got == 0.0, (dx, dy)
    # beyond 3.33 sigma nothing is drawn
    assert out.alpha[20, 30 + 17].item() == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_lowpass_filter_keeps_tiny_surfels_visible(backend):
    # a surfel much smaller than a pixel still covers its pixel with exp(-rho_2d / 2) = exp(-|d|^2)
    z = 2.0
    X, Y = (20.5 - 32) * z / 50, (10.5 - 24) * z / 50
    out = rasterize(fronto_parallel([X, Y, z], 1e-4, 0.8), torch.eye(4, dtype=torch.float64), camera(), W, H,
                    backend=backend)
    assert out.alpha[10, 20].item() == pytest.approx(0.8, abs=1e-6)
    assert out.alpha[10, 21].item() == pytest.approx(0.8 * math.exp(-1.0), rel=1e-5)
    assert out.alpha[11, 21].item() == pytest.approx(0.8 * math.exp(-2.0), rel=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_occlusion_follows_centre_depth(backend):
    red_near = fronto_parallel([0.0, 0.0, 2.0], 0.3, 0.99, (1.0, 0.0, 0.0))
    blue_far = fronto_parallel([0.0, 0.0, 3.0], 0.3, 0.99, (0.0, 0.0, 1.0))
    for scene in (Surfels.concat([red_near, blue_far]), Surfels.concat([blue_far, red_near])):
        out = rasterize(scene, torch.eye(4, dtype=torch.float64), camera(), W, H, backend=backend)
        # pixel (24, 32) sits 0.5 px from the centre: the near surfel takes ~0.99 of it
        rgb = out.rgb[24, 32]
        assert rgb[0] > 0.95 and rgb[2] < 0.02
        r2 = 0.5**2 + 0.5**2  # squared pixel offset; sigma = f s / z pixels
        a_near = 0.99 * math.exp(-r2 / (2 * (50 * 0.3 / 2.0) ** 2))
        a_far = 0.99 * math.exp(-r2 / (2 * (50 * 0.3 / 3.0) ** 2))
        assert rgb[0].item() == pytest.approx(a_near, rel=1e-6)
        assert rgb[2].item() == pytest.approx((1 - a_near) * a_far, rel=1e-5)
        assert out.depth[24, 32].item() == pytest.approx(
            (a_near * 2.0 + (1 - a_near) * a_far * 3.0) / (1 - (1 - a_near) * (1 - a_far)), rel=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_expected_depth_of_a_fronto_parallel_plane(backend):
    # a dense grid of overlapping surfels on the plane z = 2.5 renders depth 2.5 wherever something is drawn
    z = 2.5
    xs, ys = torch.meshgrid(torch.linspace(-2, 2, 41), torch.linspace(-1.5, 1.5, 31), indexing="xy")
    n = xs.numel()
    g = torch.Generator().manual_seed(3)
    plane = surfels_of(torch.stack([xs.flatten(), ys.flatten(), torch.full((n,), z)], -1),
                       torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4), torch.full((n, 2), 0.08),
                       torch.full((n,), 0.95), torch.rand(n, 3, generator=g))
    out = rasterize(plane, torch.eye(4, dtype=torch.float64), camera(), W, H, backend=backend)
    assert (out.alpha > 0.99).all()
    assert torch.allclose(out.depth, torch.full_like(out.depth, z), atol=1e-9)
    normals = out.normals / out.alpha[..., None]
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand_as(normals),
                          atol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_float64_oracle_on_a_random_scene(backend):
    scene = random_scene(300, seed=1, scale_range=(0.05, 0.2), opacity_range=(0.3, 0.99), extent=(1.0, 0.8))
    V = look_from(0.1)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    out = rasterize(scene, V, camera(), W, H, background=bg, backend=backend)
    rgb, depth, alpha, normals = render_oracle(scene.means, scene.quats, scale_np(scene), scene.opacities,
                                               scene.colors, V, camera(), W, H, background=bg.numpy())
    assert alpha.max() > 0.999 and (alpha == 0).sum() > 0  # early-stopped, covered and empty pixels
    np.testing.assert_allclose(out.rgb.numpy(), rgb, atol=1e-9)
    np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-9)
    np.testing.assert_allclose(out.depth.numpy(), depth, atol=1e-8)
    np.testing.assert_allclose(out.normals.numpy(), normals, atol=1e-9)


def scale_np(s: Surfels) -> np.ndarray:
    return s.scales.numpy()


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_and_culled_scenes_render_the_background(backend):
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    for scene in (Surfels.empty(dtype=torch.float64), fronto_parallel([0.0, 0.0, -1.0], 0.2, 0.9),
                  fronto_parallel([50.0, 0.0, 2.0], 0.2, 0.9)):
        out = rasterize(scene, torch.eye(4, dtype=torch.float64), camera(), W, H, background=bg, backend=backend)
        assert out.rgb.shape == (H, W, 3) and out.depth.shape == (H, W)
        assert torch.equal(out.rgb, bg.expand(H, W, 3))
        assert not out.alpha.any() and not out.depth.any() and not out.normals.any()


def test_bad_input_is_rejected_with_a_clear_message():
    scene = fronto_parallel([0.0, 0.0, 2.0], 0.2, 0.9)
    eye = torch.eye(4, dtype=torch.float64)
    with pytest.raises(ValueError, match="backend"):
        rasterize(scene, eye, camera(), W, H, backend="vulkan")
    with pytest.raises(ValueError, match="viewmat"):
        rasterize(scene, eye[:3], camera(), W, H)
    with pytest.raises(ValueError, match="K must"):
        rasterize(scene, eye, camera()[:2], W, H)
    with pytest.raises(ValueError, match="image size"):
        rasterize(scene, eye, camera(), 0, H)
    with pytest.raises(ValueError, match="background"):
        rasterize(scene, eye, camera(), W, H, background=torch.zeros(4))
    with pytest.raises(ValueError, match="non-finite"):
        rasterize(scene, eye * float("nan"), camera(), W, H)


SMALL_K = torch.tensor([[20.0, 0.0, 12.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def weighted_sum(out: RenderResult, weights: list[torch.Tensor]) -> torch.Tensor:
    """A scalar loss that touches every output channel with its own random weights."""
    return sum((w * o).sum() for w, o in zip(weights, out))


def random_weights(width: int, height: int, seed: int, dtype=torch.float64) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    shapes = [(height, width, 3), (height, width), (height, width), (height, width, 3)]
    return [torch.rand(s, generator=g, dtype=torch.float64).to(dtype) * 2 - 1 for s in shapes]


@pytest.mark.usefixtures("single_thread")
def test_reference_gradients_match_finite_differences():
    """float64 gradcheck of the whole pipeline (projection + compositing) on a tiny scene, pose included."""
    scene = random_scene(12, seed=5, scale_range=(0.1, 0.3))
    weights = random_weights(24, 20, seed=9)
    bg = torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64)
    names = ("means", "quats", "scales", "opacities", "colors")
    params = {k: getattr(scene, k).clone().requires_grad_(True) for k in names}
    V = look_from(0.05).requires_grad_(True)

    def f(means, quats, scales, opacities, colors, viewmat):
        out = rasterize(surfels_of(means, quats, scales, opacities, colors), viewmat, SMALL_K, 24, 20,
                        background=bg, backend="reference")
        assert out.alpha.max() > 0.5
        return weighted_sum(out, weights)

    # finite differences can step across the alpha >= 1/255 and tile thresholds; keep eps small
    assert torch.autograd.gradcheck(f, (*params.values(), V), eps=1e-7, atol=1e-5, rtol=1e-4, fast_mode=True)
