import pytest
import torch

from worker.geometry import quat_to_rotmat
from worker.mapping.voxelize import valid_pixel_mask, voxelize


def grid(H: int, W: int, gen: torch.Generator, depth: torch.Tensor | None = None):
    depth = torch.full((H, W), 2.0, dtype=torch.float64) if depth is None else depth
    means = torch.stack([torch.rand(H, W, generator=gen, dtype=torch.float64) - 0.5,
                         torch.rand(H, W, generator=gen, dtype=torch.float64) - 0.5, depth], dim=-1)
    base = torch.tensor([0.9, 0.1, 0.3, -0.2], dtype=torch.float64)
    noise = 0.05 * torch.randn(H, W, 4, generator=gen, dtype=torch.float64)
    quats = torch.nn.functional.normalize(base + noise, dim=-1)
    return dict(
        means=means,
        quats=quats,
        scales=torch.rand(H, W, 2, generator=gen, dtype=torch.float64) * 0.01 + 0.001,
        opacities=torch.rand(H, W, generator=gen, dtype=torch.float64),
        colors=torch.rand(H, W, 3, generator=gen, dtype=torch.float64),
    )


def test_flat_blocks_are_averaged_with_aligned_quaternions():
    gen = torch.Generator().manual_seed(0)
    g = grid(4, 6, gen)
    g["quats"][0, 1] *= -1  # same rotation, opposite sign: must not cancel in the average
    out = voxelize(**g, keyframe_id=7)
    assert len(out.surfels) == 6 and bool(out.merged.all())
    assert torch.equal(out.surfels.keyframe_ids, torch.full((6,), 7))
    block = (slice(0, 2), slice(0, 2))
    assert torch.allclose(out.surfels.means[0], g["means"][block].reshape(4, 3).mean(0))
    assert torch.allclose(out.surfels.colors[0], g["colors"][block].reshape(4, 3).mean(0))
    assert torch.allclose(out.surfels.scales[0], g["scales"][block].reshape(4, 2).mean(0))
    assert torch.allclose(out.surfels.opacities[0], g["opacities"][block].reshape(4).mean())
    q = g["quats"][block].reshape(4, 4).clone()
    q[1] = -q[1]
    expected = torch.nn.functional.normalize(q.sum(0), dim=0)
    assert torch.allclose(out.surfels.quats[0], expected)
    # the merged rotation is close to every member's rotation (no sign cancellation)
    R = quat_to_rotmat(out.surfels.quats[0])
    for member in g["quats"][block].reshape(4, 4):
        assert (quat_to_rotmat(member) - R).abs().max() < 0.35
    assert out.pixels[1].tolist() == [0, 2]


def test_blocks_with_depth_jump_are_kept_untouched():
    gen = torch.Generator().manual_seed(1)
    depth = torch.full((4, 4), 2.0, dtype=torch.float64)
    depth[0, 0] = 3.0  # 50 % jump inside the top-left block
    g = grid(4, 4, gen, depth)
    out = voxelize(**g, tau_d=0.05)
    assert int(out.merged.sum()) == 3 and int((~out.merged).sum()) == 4
    kept = out.surfels.select(~out.merged)
    assert torch.equal(kept.means, g["means"][:2, :2].reshape(4, 3))
    assert torch.allclose(kept.colors, g["colors"][:2, :2].reshape(4, 3))
    assert sorted(map(tuple, out.pixels[~out.merged].tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    # absolute threshold: a 1.0 jump is within tau_d = 1.5
    assert bool(voxelize(**g, tau_d=1.5, relative=False).merged.all())


def test_invalid_pixels_are_dropped_and_odd_edges_kept():
    gen = torch.Generator().manual_seed(2)
    g = grid(5, 4, gen)
    conf = torch.ones(5, 4)
    conf[0, 0] = 0.0
    g["means"][1, 3, 2] = -1.0  # behind the camera
    valid = valid_pixel_mask(g["means"], conf, conf_threshold=0.5)
    out = voxelize(**g, valid=valid)
    # rows 0-3 give 4 blocks; the top-left block averages only its 3 valid surfels
    assert torch.allclose(out.surfels.means[0], g["means"][:2, :2].reshape(4, 3)[1:].mean(0))
    assert torch.allclose(out.surfels.means[1], g["means"][:2, 2:].reshape(4, 3)[[0, 1, 2]].mean(0))
    # the odd last row stays per-pixel
    last = out.pixels[~out.merged]
    assert last.tolist() == [[4, 0], [4, 1], [4, 2], [4, 3]]
    # a fully invalid block vanishes
    g2 = grid(2, 2, gen)
    assert len(voxelize(**g2, valid=torch.zeros(2, 2, dtype=torch.bool)).surfels) == 0


def test_bad_shapes_raise():
    gen = torch.Generator().manual_seed(3)
    g = grid(2, 2, gen)
    g["colors"] = g["colors"][..., :2]
    with pytest.raises(ValueError, match="colors"):
        voxelize(**g)
