import pytest
import torch

from worker.geometry import quat_to_rotmat, sim3_apply, sim3_from_quat, sim3_inverse
from worker.mapping import Surfels
from worker.mapping.loop_correction import correct_map


def random_surfels(n: int, gen: torch.Generator) -> Surfels:
    return Surfels(
        means=torch.randn(n, 3, generator=gen),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
        scales=torch.rand(n, 2, generator=gen) * 0.1 + 0.01,
        opacities=torch.rand(n, generator=gen),
        colors=torch.rand(n, 3, generator=gen),
        keyframe_ids=torch.arange(n) % 3,
    )


def pose(q, t, s):
    return sim3_from_quat(torch.tensor(q, dtype=torch.float64), torch.tensor(t, dtype=torch.float64), s)


def test_surfels_follow_their_keyframe_rigidly():
    gen = torch.Generator().manual_seed(0)
    surfels = random_surfels(30, gen)
    old = {0: pose([1, 0, 0, 0], [0, 0, 0], 1.0), 1: pose([0.9, 0.2, -0.1, 0.3], [1, 2, 3], 1.3),
           2: pose([0.5, 0.5, 0.5, 0.5], [-1, 0, 2], 0.8)}
    new = {1: pose([0.8, -0.3, 0.1, 0.2], [0.5, 1, -2], 2.0), 2: old[2].clone()}
    out = correct_map(surfels, old, new)
    # keyframe 0 (no update) and keyframe 2 (unchanged pose) do not move
    for k in (0, 2):
        m = surfels.keyframe_ids == k
        assert torch.allclose(out.means[m], surfels.means[m], atol=1e-6)
        assert torch.allclose(out.quats[m], surfels.quats[m], atol=1e-6)
    m = surfels.keyframe_ids == 1
    # camera-frame coordinates w.r.t. the keyframe are preserved exactly: T_new^-1 x' == T_old^-1 x
    cam_before = sim3_apply(sim3_inverse(old[1]), surfels.means[m].double())
    cam_after = sim3_apply(sim3_inverse(new[1]), out.means[m].double())
    assert torch.allclose(cam_before, cam_after, atol=1e-5)
    scale_ratio = 2.0 / 1.3
    assert torch.allclose(out.scales[m], surfels.scales[m] * scale_ratio, atol=1e-6)
    # rotations: R_new^T R' == R_old^T R
    R_old, R_new = old[1][:3, :3] / 1.3, new[1][:3, :3] / 2.0
    before = R_old.T @ quat_to_rotmat(surfels.quats[m].double())
    after = R_new.T @ quat_to_rotmat(out.quats[m].double())
    assert torch.allclose(before, after, atol=1e-5)
    assert torch.equal(out.colors, surfels.colors) and torch.equal(out.keyframe_ids, surfels.keyframe_ids)


def test_unknown_keyframe_raises():
    surfels = random_surfels(3, torch.Generator().manual_seed(1))
    with pytest.raises(ValueError, match="unknown keyframe"):
        correct_map(surfels, {}, {5: torch.eye(4)})
