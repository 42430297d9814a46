"""The compiled CPU path against the pure-torch reference: values, gradients (pose included), fallback."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch
from native_fallback import run_without_compiler
from test_rasterize import (  # noqa: F401 (single_thread is a fixture)
    SMALL_K,
    camera,
    look_from,
    random_scene,
    random_weights,
    single_thread,
    surfels_of,
    weighted_sum,
)

from worker.mapping import Surfels, raster_cpu, rasterize
from worker.mapping.raster_projection import project_surfels
from worker.mapping.rasterize import visible_mask

W, H = 64, 48
ATTRIBUTES = ("means", "quats", "scales", "opacities", "colors")
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module", autouse=True)
def _compiled() -> None:
    if shutil.which(os.environ.get("CXX", "c++").split()[0]) is None:
        pytest.skip("no C++ compiler on this machine: the compiled path cannot be built")
    assert raster_cpu.available(), raster_cpu.load_error()


def render_with_grads(scene: Surfels, viewmat: torch.Tensor, backend: str, weights, K=None, size=(W, H),
                      background=None):
    """Outputs and d(weighted sum)/d(every surfel attribute and the viewmat)."""
    leaves = {k: getattr(scene, k).detach().clone().requires_grad_(True) for k in ATTRIBUTES}
    V = viewmat.detach().clone().requires_grad_(True)
    bg = None if background is None else background.detach().clone().requires_grad_(True)
    out = rasterize(surfels_of(*(leaves[k] for k in ATTRIBUTES), dtype=scene.means.dtype), V,
                    camera(scene.means.dtype) if K is None else K, *size, background=bg, backend=backend)
    weighted_sum(out, weights).backward()
    grads = {k: v.grad for k, v in leaves.items()} | {"viewmat": V.grad}
    if bg is not None:
        grads["background"] = bg.grad
    return out, grads


def assert_close_scaled(a: torch.Tensor, b: torch.Tensor, tol: float, what: str) -> None:
    """|a - b| <= tol * max(1, max |b|) elementwise."""
    scale = max(1.0, b.abs().max().item())
    err = (a - b).abs().max().item()
    assert err <= tol * scale, f"{what}: max abs error {err:.3g} (scale {scale:.3g})"


# float64: the fast path equals the reference to rounding. float32: both paths sit ~1e-5 (values) and ~2-5e-5
# (gradients, relative to the largest entry) from the exact float64 answer, differently rounded (the compiled
# projection runs in float64 internally), so the float32 fast path is compared with the float64 reference at 1e-5
# (values) and 5e-5 (gradients): the reference's own float32 error is of the same size.
@pytest.mark.parametrize("dtype, tol, grad_tol", [(torch.float64, 1e-10, 1e-10), (torch.float32, 1e-5, 5e-5)])
def test_fast_path_equals_reference_values_and_gradients(dtype, tol, grad_tol):
    scene = random_scene(300, seed=11, dtype=torch.float64, scale_range=(0.02, 0.2), opacity_range=(0.2, 0.99),
                         extent=(1.2, 0.9))
    V = look_from(-0.08, t=(0.1, 0.05, -0.2))
    bg = torch.tensor([0.5, 0.2, 0.9], dtype=torch.float64)
    weights = random_weights(W, H, seed=2)
    ref_out, ref_grads = render_with_grads(scene, V, "reference", weights, background=bg)
    cpu_out, cpu_grads = render_with_grads(scene.to(dtype=dtype), V.to(dtype), "cpu", [w.to(dtype) for w in weights],
                                           K=camera(dtype), background=bg.to(dtype))
    assert ref_out.alpha.max() > 0.999 and (ref_out.alpha == 0).any()
    for name, a, b in zip(ref_out._fields, cpu_out, ref_out):
        assert a.dtype == dtype
        assert_close_scaled(a.double(), b, tol, name)
    for name, g in ref_grads.items():
        assert g is not None and g.abs().max() > 0, name
        assert cpu_grads[name].dtype == dtype
        assert_close_scaled(cpu_grads[name].double(), g, grad_tol, f"d/d{name}")


@pytest.mark.usefixtures("single_thread")
def test_fast_path_gradients_match_finite_differences():
    """float64 gradcheck of the whole pipeline with the compiled compositor."""
    scene = random_scene(12, seed=5, scale_range=(0.1, 0.3))
    weights = random_weights(24, 20, seed=9)
    bg = torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64)

    def f(means, quats, scales, opacities, colors, viewmat, background):
        out = rasterize(surfels_of(means, quats, scales, opacities, colors), viewmat, SMALL_K, 24, 20,
                        background=background, backend="cpu")
        return weighted_sum(out, weights)

    inputs = [getattr(scene, k).clone().requires_grad_(True) for k in ATTRIBUTES]
    pose = look_from(0.05).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (*inputs, pose, bg.requires_grad_(True)), eps=1e-7, atol=1e-5, rtol=1e-4,
                                    fast_mode=True)


@pytest.mark.usefixtures("single_thread")
def test_compositor_gradients_match_finite_differences_with_early_termination():
    """gradcheck of the compiled compositing stage alone, on a pile of opaque surfels that stops pixels early."""
    g = torch.Generator().manual_seed(4)
    M, size = 24, 20
    T = torch.zeros(M, 3, 3, dtype=torch.float64)
    scale = torch.rand(M, 2, generator=g, dtype=torch.float64) * 3 + 2  # 2-5 px footprints
    centre = torch.rand(M, 2, generator=g, dtype=torch.float64) * 12 + 4
    T[:, 0, 0], T[:, 1, 1], T[:, 2, 2] = scale[:, 0], scale[:, 1], 1.0
    T[:, 0, 1] = torch.rand(M, generator=g, dtype=torch.float64)  # shear: not axis-aligned
    T[:, :2, 2] = centre
    T[:, 2, :2] = torch.randn(M, 2, generator=g, dtype=torch.float64) * 0.02  # slight perspective
    planes = torch.stack([torch.cross(T[:, 1], T[:, 2], dim=-1), torch.cross(T[:, 2], T[:, 0], dim=-1),
                          torch.cross(T[:, 0], T[:, 1], dim=-1)], 1)
    means2d = centre + torch.randn(M, 2, generator=g, dtype=torch.float64) * 0.1
    opacities = torch.rand(M, generator=g, dtype=torch.float64) * 0.3 + 0.69
    features = torch.rand(M, 3, generator=g, dtype=torch.float64)
    radii = torch.full((M, 2), 16, dtype=torch.int32)
    depths = torch.rand(M, generator=g, dtype=torch.float64)
    weights = torch.rand(size, size, 3, generator=g, dtype=torch.float64)
    alpha_weights = torch.rand(size, size, generator=g, dtype=torch.float64)

    def f(planes, means2d, opacities, features):
        feat, alpha = raster_cpu.composite_cpu(planes, T, means2d, opacities, features, radii, depths, size, size)
        return (feat * weights).sum() + (alpha * alpha_weights).sum()

    with torch.no_grad():
        _, alpha = raster_cpu.composite_cpu(planes, T, means2d, opacities, features, radii, depths, size, size)
    assert (alpha > 1 - 1e-3).sum() > 20  # many pixels hit the T <= 1e-4 stop
    inputs = [t.clone().requires_grad_(True) for t in (planes, means2d, opacities, features)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_culled_surfels_get_zero_gradients_and_leave_the_image_unchanged():
    """Surfels behind the camera, nearer than the near plane or off-screen: no effect on the image, zero grads."""
    visible = random_scene(40, seed=3, scale_range=(0.05, 0.2))
    culled = surfels_of([[0.0, 0.0, -1.0], [0.0, 0.0, -0.095], [40.0, 0.0, 2.0], [0.0, -30.0, 2.0]],
                        torch.randn(4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64),
                        [[0.2, 0.2]] * 4, [0.9] * 4, [[1.0, 0.0, 0.0]] * 4)
    weights = random_weights(W, H, seed=4)
    alone, _ = render_with_grads(visible, look_from(0.0), "cpu", weights)
    out, grads = render_with_grads(Surfels.concat([visible, culled]), look_from(0.0), "cpu", weights)
    for a, b in zip(out, alone):
        assert torch.equal(a, b)
    for name in ATTRIBUTES:
        assert not grads[name][40:].any(), name
        assert grads[name][:40].abs().max() > 0, name


def test_visible_mask_is_the_rasterizers_culling():
    """Rendering only the surfels `visible_mask` keeps gives the same image; compiled and torch culling agree."""
    scene = Surfels.concat([random_scene(200, seed=8, scale_range=(0.05, 0.2), extent=(3.0, 2.5)),
                            surfels_of([[0.0, 0.0, -1.0]], [[1.0, 0, 0, 0]], [[0.2, 0.2]], [0.9], [[1.0, 0, 0]])])
    V = look_from(0.3)
    mask = visible_mask(scene, V, camera(), W, H)
    assert mask.dtype == torch.bool and mask.shape == (len(scene),)
    assert 0 < int(mask.sum()) < len(scene) - 20 and not mask[-1]
    torch_ids = project_surfels(scene.means, scene.quats, scene.scales, V, camera(), W, H).ids
    assert torch.equal(mask.nonzero()[:, 0], torch_ids)
    full, subset = rasterize(scene, V, camera(), W, H), rasterize(scene.select(mask), V, camera(), W, H)
    for a, b in zip(full, subset):
        assert torch.equal(a, b)


def test_outputs_and_gradients_do_not_depend_on_the_thread_count():
    """Tiles are independent, per-surfel sums run in a fixed order: 1 and 2 threads give identical bits."""
    scene = random_scene(3000, seed=5, dtype=torch.float32, scale_range=(0.02, 0.2), opacity_range=(0.2, 0.99),
                         extent=(1.2, 0.9))
    weights = [w.float() for w in random_weights(W, H, seed=2)]
    before = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            runs.append(render_with_grads(scene, look_from(0.05, dtype=torch.float32), "cpu", weights,
                                          K=camera(torch.float32)))
    finally:
        torch.set_num_threads(before)
    (out1, grads1), (out2, grads2) = runs
    with raster_cpu.using_threads(3):  # the kernels' own thread count, whatever torch uses
        assert raster_cpu.worker_threads() == 3
        runs.append(render_with_grads(scene, look_from(0.05, dtype=torch.float32), "cpu", weights,
                                      K=camera(torch.float32)))
    assert raster_cpu.worker_threads() == torch.get_num_threads()
    with pytest.raises(ValueError, match="thread count"), raster_cpu.using_threads(0):
        pass
    out3, grads3 = runs[2]
    assert all(torch.equal(a, b) for a, b in zip(out1, out3))
    assert all(torch.equal(g, grads3[name]) for name, g in grads1.items())
    assert out1.alpha.max() > 0.99
    for a, b in zip(out1, out2):
        assert torch.equal(a, b)
    for name, g in grads1.items():
        assert torch.equal(g, grads2[name]), name


def test_pose_gradient_descends():
    """A step against d loss / d translation (through viewmat) lowers a photometric loss: pose refinement works."""
    scene = random_scene(400, seed=21, dtype=torch.float32, scale_range=(0.05, 0.2), opacity_range=(0.5, 0.99),
                         extent=(1.2, 0.9))
    K = camera(torch.float32)
    target = rasterize(scene, torch.eye(4), K, W, H).rgb

    def loss_at(t: torch.Tensor) -> torch.Tensor:
        V = torch.eye(4).index_put((torch.arange(3), torch.full((3,), 3)), t)
        return (rasterize(scene, V, K, W, H, backend="cpu").rgb - target).square().mean()

    t = torch.tensor([0.03, -0.02, 0.02], requires_grad=True)
    loss = loss_at(t)
    loss.backward()
    assert t.grad.norm() > 0
    with torch.no_grad():
        step = 0.01 * t.grad / t.grad.norm()
        assert loss_at(t - step) < loss < loss_at(t + step)


def test_falls_back_to_reference_when_the_compiler_fails(tmp_path):
    script = (
        "import logging, torch, sys\n"
        "sys.path.insert(0, 'tests/mapping')\n"
        "logging.basicConfig(level=logging.WARNING)\n"
        "from test_rasterize import random_scene, camera\n"
        "from worker.mapping import rasterize, raster_cpu\n"
        "s = random_scene(50, seed=1)\n"
        "a = rasterize(s, torch.eye(4, dtype=torch.float64), camera(), 32, 24, backend='cpu')\n"
        "b = rasterize(s, torch.eye(4, dtype=torch.float64), camera(), 32, 24, backend='reference')\n"
        "assert not raster_cpu.available()\n"
        "assert torch.equal(a.rgb, b.rgb)\n"
        "print('FELL BACK', raster_cpu.load_error())\n"
    )
    result = run_without_compiler(script, tmp_path)
    assert "FELL BACK" in result.stdout
    assert "compiled CPU rasterizer unavailable" in result.stderr
