import torch

from worker.geometry import quat_to_rotmat, sim3_from_quat
from worker.mapping import Surfels


def random_surfels(n: int, gen: torch.Generator) -> Surfels:
    return Surfels(
        means=torch.randn(n, 3, generator=gen, dtype=torch.float64),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen, dtype=torch.float64), dim=-1),
        scales=torch.rand(n, 2, generator=gen, dtype=torch.float64) * 0.1,
        opacities=torch.rand(n, generator=gen, dtype=torch.float64),
        colors=torch.rand(n, 3, generator=gen, dtype=torch.float64),
        keyframe_ids=torch.arange(n) % 3,
    )


def test_select_concat_and_shape_checks():
    gen = torch.Generator().manual_seed(0)
    a, b = random_surfels(5, gen), random_surfels(3, gen)
    both = Surfels.concat([a, b])
    assert len(both) == 8
    assert torch.equal(both.select(torch.arange(5, 8)).means, b.means)
    assert len(both.select(both.keyframe_ids == 0)) == int((both.keyframe_ids == 0).sum())
    assert both.to(dtype=torch.float32).means.dtype == torch.float32
    assert both.to(dtype=torch.float32).keyframe_ids.dtype == torch.int64
    try:
        Surfels(a.means, a.quats[:, :3], a.scales, a.opacities, a.colors, a.keyframe_ids)
    except ValueError as err:
        assert "quats" in str(err)
    else:
        raise AssertionError("bad shape accepted")


def test_transform_follows_paper_eq17():
    gen = torch.Generator().manual_seed(1)
    s = random_surfels(10, gen)
    T = sim3_from_quat(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64),
                       torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64), 1.7)
    out = s.transform(T)
    R = T[:3, :3] / 1.7
    assert torch.allclose(out.means, s.means @ T[:3, :3].T + T[:3, 3])
    assert torch.allclose(quat_to_rotmat(out.quats), R @ quat_to_rotmat(s.quats), atol=1e-12)
    assert torch.allclose(out.scales, s.scales * 1.7)
    per = s.transform_per_surfel(T.expand(10, 4, 4))
    assert torch.allclose(per.means, out.means) and torch.allclose(per.quats, out.quats)
