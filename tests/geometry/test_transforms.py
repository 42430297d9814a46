import gtsam
import numpy as np
import pytest
import torch

from worker.geometry import (
    Intrinsics,
    make_sim3,
    project_points,
    quat_multiply,
    quat_to_rotmat,
    rotmat_to_quat,
    sim3_apply,
    sim3_decompose,
    sim3_from_quat,
    sim3_inverse,
    so3_exp,
    so3_log,
    umeyama,
    unproject_depth,
)
from worker.geometry.gtsam_bridge import sim3_from_gtsam, sim3_to_gtsam


def random_sim3(gen: torch.Generator, n: int = 1) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    t = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    s = torch.rand(n, generator=gen, dtype=torch.float64) * 2 + 0.2
    return sim3_from_quat(q, t, s)


def to_gtsam(T: torch.Tensor) -> gtsam.Similarity3:
    """Independent conversion: GTSAM's Similarity3(R, t, s) maps p -> s (R p + t)."""
    s, R, t = sim3_decompose(T)
    return gtsam.Similarity3(gtsam.Rot3(R.numpy()), (t / s).numpy(), float(s))


def gtsam_matrix(S: gtsam.Similarity3) -> np.ndarray:
    M = S.matrix()
    return M / M[3, 3]


def test_quaternion_matches_gtsam_and_round_trips():
    gen = torch.Generator().manual_seed(1)
    q = torch.nn.functional.normalize(torch.randn(50, 4, generator=gen, dtype=torch.float64), dim=-1)
    R = quat_to_rotmat(q)
    for qi, Ri in zip(q, R):
        w, x, y, z = qi.tolist()
        np.testing.assert_allclose(gtsam.Rot3.Quaternion(w, x, y, z).matrix(), Ri.numpy(), atol=1e-12)
    q_back = rotmat_to_quat(R)
    same = torch.minimum((q_back - q).abs().amax(-1), (q_back + q).abs().amax(-1))
    assert same.max() < 1e-10
    assert (q_back[:, 0] >= 0).all()


def test_rotmat_to_quat_near_180_degrees():
    R = quat_to_rotmat(torch.tensor([[1e-9, 1.0, 0.0, 0.0], [0.0, 0.0, 0.7071, 0.7071]], dtype=torch.float64))
    assert torch.allclose(quat_to_rotmat(rotmat_to_quat(R)), R, atol=1e-9)


def test_quat_multiply_is_rotation_composition():
    gen = torch.Generator().manual_seed(2)
    a, b = torch.randn(2, 10, 4, generator=gen, dtype=torch.float64)
    assert torch.allclose(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-12)


def test_sim3_compose_inverse_apply_agree_with_gtsam():
    gen = torch.Generator().manual_seed(3)
    A, B = random_sim3(gen, 2)
    p = torch.randn(7, 3, generator=gen, dtype=torch.float64)
    gA, gB = to_gtsam(A), to_gtsam(B)
    np.testing.assert_allclose((A @ B).numpy(), gtsam_matrix(gA.compose(gB)), atol=1e-10)
    np.testing.assert_allclose(sim3_inverse(A).numpy(), gtsam_matrix(gA.inverse()), atol=1e-10)
    expected = np.stack([gA.transformFrom(pi.numpy()) for pi in p])
    np.testing.assert_allclose(sim3_apply(A, p).numpy(), expected, atol=1e-10)
    assert torch.allclose(sim3_inverse(A) @ A, torch.eye(4, dtype=torch.float64), atol=1e-12)
    s, R, t = sim3_decompose(A)
    assert torch.allclose(make_sim3(R, t, s), A, atol=1e-12)
    assert torch.allclose(sim3_from_gtsam(sim3_to_gtsam(A)), A, atol=1e-12)
    via_gtsam = sim3_to_gtsam(A).transformFrom(p[0].numpy())
    np.testing.assert_allclose(via_gtsam, sim3_apply(A, p[:1])[0].numpy(), atol=1e-12)


def test_so3_exp_log_round_trip():
    gen = torch.Generator().manual_seed(4)
    w = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(20, 1, generator=gen, dtype=torch.float64) * 3.0
    assert torch.allclose(so3_log(so3_exp(w)), w, atol=1e-9)
    np.testing.assert_allclose(so3_exp(w[0]).numpy(), gtsam.Rot3.Expmap(w[0].numpy()).matrix(), atol=1e-12)
    assert torch.allclose(so3_exp(torch.zeros(3, dtype=torch.float64)), torch.eye(3, dtype=torch.float64))


@pytest.mark.parametrize("with_scale", [True, False])
def test_umeyama_recovers_known_similarity(with_scale):
    gen = torch.Generator().manual_seed(5)
    T = random_sim3(gen)[0]
    if not with_scale:
        s, R, t = sim3_decompose(T)
        T = make_sim3(R, t)
    src = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    dst = sim3_apply(T, src)
    s, R, t = umeyama(src, dst, with_scale=with_scale)
    assert torch.allclose(make_sim3(R, t, s), T, atol=1e-9)


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(ValueError, match="umeyama"):
        umeyama(torch.zeros(2, 3), torch.zeros(2, 3))


def test_camera_unproject_project_round_trip():
    intr = Intrinsics(525.0, 520.0, 319.5, 239.5, 640, 480)
    K = intr.matrix(torch.float64)
    depth = torch.rand(48, 64, dtype=torch.float64) + 0.5
    pts = unproject_depth(depth, K)
    uv, z = project_points(pts, K)
    assert torch.allclose(z, depth)
    assert torch.allclose(uv[5, 7], torch.tensor([7.5, 5.5], dtype=torch.float64))
    half = intr.scaled(320, 240)
    assert half.fx == 262.5 and half.cx == 159.75
    with pytest.raises(ValueError):
        Intrinsics(0.0, 1.0, 0.0, 0.0, 10, 10)


def test_se3_part_removes_the_scale_and_keeps_the_translation() -> None:
    from worker.geometry import make_sim3, se3_part, so3_exp

    R = so3_exp(torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64))
    t = torch.tensor([1.0, 2.0, -3.0], dtype=torch.float64)
    rigid = se3_part(make_sim3(R, t, 2.5).numpy())
    np.testing.assert_allclose(rigid, make_sim3(R, t).numpy(), atol=1e-12)


def test_sim3_blend_goes_from_one_similarity_to_the_other():
    from worker.geometry import sim3_blend

    A = make_sim3(so3_exp(torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)),
                  torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), 2.0)
    turn = so3_exp(torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64))
    B = make_sim3(sim3_decompose(A)[1] @ turn, torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64), 8.0)
    assert torch.allclose(sim3_blend(A, B, 0.0), A, atol=1e-12) and torch.allclose(sim3_blend(A, B, 1.0), B, atol=1e-12)
    s, R, t = sim3_decompose(sim3_blend(A, B, 0.5))
    assert torch.allclose(s, torch.tensor(4.0, dtype=torch.float64))  # geometric in the scale
    assert torch.allclose(t, torch.tensor([2.0, 2.0, 2.0], dtype=torch.float64))
    half_turn = sim3_decompose(A)[1].T @ R
    assert torch.allclose(so3_log(half_turn), torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64), atol=1e-9)


def test_nearest_sim3_removes_shear_and_keeps_a_similarity():
    from worker.geometry import nearest_sim3, sim3_inverse

    rng = np.random.default_rng(0)
    R = cv2_free_rotation(rng)
    T = np.eye(4)
    T[:3, :3] = 1.7 * R
    T[:3, 3] = [0.3, -1.2, 2.0]
    np.testing.assert_allclose(nearest_sim3(T), T, atol=1e-12)  # a similarity stays as it is
    sheared = T.copy()
    sheared[:3, :3] += 1e-4 * rng.standard_normal((3, 3))
    fixed = nearest_sim3(sheared)
    block = fixed[:3, :3] / np.cbrt(np.linalg.det(fixed[:3, :3]))
    np.testing.assert_allclose(block.T @ block, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(fixed[:3, 3], T[:3, 3])
    # chains of products with closed-form inverses: the shear compounds without the projection, not with it
    drifting, kept = sheared, fixed
    for _ in range(60):
        drifting = drifting @ sim3_inverse(torch.from_numpy(drifting)).numpy() @ drifting
        kept = nearest_sim3(kept @ sim3_inverse(torch.from_numpy(kept)).numpy() @ kept)

    def shear(m):
        b = m[:3, :3] / np.cbrt(abs(np.linalg.det(m[:3, :3])))
        return np.abs(b.T @ b - np.eye(3)).max()
    assert shear(kept) < 1e-10
    assert not shear(drifting) <= 1e-3  # grown past 1e-3, or blown up to NaN


def cv2_free_rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q if np.linalg.det(q) > 0 else -q
