"""The map in the web formats (SPZ v3, antimatter15 .splat): byte layouts as their specifications say, and the
round-trip error against the PLY within the quantisation each format has (positions, colours, opacity, scales,
rotations and surfel normals). The browser test (tests/viewer/test_splat_viewer.py) reads the same files with
Spark's own loader."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest
import torch
from mapping_scene import camera_pose, voxelized_surfels

from worker.geometry import quat_to_rotmat
from worker.mapping import Surfels
from worker.mapping.map_formats import FORMATS, encode_map
from worker.mapping.ply import surfels_to_ply_bytes
from worker.mapping.splat_arrays import SplatArrays, splat_arrays_from_ply
from worker.mapping.splat_file import decode_splat, encode_splat
from worker.mapping.spz import decode_spz, encode_spz, fractional_bits_for


def _varied_surfels(n: int = 3000, seed: int = 0) -> Surfels:
    """Surfels with every orientation, sizes from 0.1 mm to 10 cm, the whole opacity and colour range."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    return Surfels(means=torch.rand(n, 3, generator=g) * 8 - 4, quats=q / q.norm(dim=1, keepdim=True),
                   scales=torch.exp(torch.rand(n, 2, generator=g) * 6.9 - 9.2),
                   opacities=torch.rand(n, generator=g) * 0.98 + 0.01, colors=torch.rand(n, 3, generator=g),
                   keyframe_ids=torch.zeros(n, dtype=torch.int64))


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle of the rotation between unit quaternions (|q1 - q2| = 2 sin(angle / 4); q and -q alike)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    b = b * np.where((a * b).sum(axis=1) < 0, -1.0, 1.0)[:, None]
    return np.degrees(4 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2, 0.0, 1.0)))


def _normals(quats: np.ndarray) -> np.ndarray:
    return quat_to_rotmat(torch.from_numpy(quats.astype(np.float64)))[:, :, 2].numpy()


@pytest.fixture(scope="module")
def reference() -> tuple[bytes, SplatArrays]:
    ply = surfels_to_ply_bytes(_varied_surfels())
    return ply, splat_arrays_from_ply(ply)


def test_ply_reads_as_flat_gaussians_with_the_surfels_values():
    surfels = _varied_surfels(500)
    for variant in ("3dgs", "2dgs"):
        arrays = splat_arrays_from_ply(surfels_to_ply_bytes(surfels, variant))
        np.testing.assert_allclose(arrays.means, surfels.means.numpy(), atol=1e-6)
        np.testing.assert_allclose(arrays.scales[:, :2], surfels.scales.numpy(), rtol=1e-5)
        assert arrays.scales[:, 2].max() < 1e-4  # a flat Gaussian: zero (2dgs) or exp(-10) (3dgs)
        np.testing.assert_allclose(arrays.opacities, surfels.opacities.numpy(), atol=1e-5)
        np.testing.assert_allclose(arrays.colors, surfels.colors.numpy(), atol=1e-5)
        assert _rotation_error_deg(arrays.quats, surfels.quats.numpy()).max() < 0.01


def test_spz_round_trip_error_is_the_formats_quantisation(reference):
    _, ref = reference
    data = encode_spz(ref)
    back = decode_spz(data)
    bits = fractional_bits_for(ref.means)
    assert bits == 12
    assert np.abs(back.means - ref.means).max() <= 0.5 / 2 ** bits + 1e-6
    # colour is the SH DC coefficient in a byte with 0.15 * 255 steps: 1 / (0.15 * 255) * C0 in RGB
    assert np.abs(back.colors - ref.colors).max() <= 0.5 / (0.15 * 255) * 0.2821 + 1e-5
    assert np.abs(back.opacities - ref.opacities).max() <= 0.5 / 255 + 1e-6
    log_error = np.abs(np.log(back.scales[:, :2] / ref.scales[:, :2]))
    assert log_error.max() <= 0.5 / 16 + 1e-5  # (ln s + 10) * 16 in a byte
    assert back.scales[:, 2].max() <= np.exp(-10.0) * 1.0001  # the flat axis stays at the smallest code
    rotation = _rotation_error_deg(back.quats, ref.quats)
    assert rotation.max() < 0.5 and rotation.mean() < 0.2, (rotation.max(), rotation.mean())
    normal_error = np.degrees(np.arccos(np.clip((_normals(back.quats) * _normals(ref.quats)).sum(1), -1, 1)))
    assert normal_error.max() < 0.5


def test_spz_layout_follows_the_specification(reference):
    _, ref = reference
    raw = gzip.decompress(encode_spz(ref))
    magic, version, count, sh_degree, bits, flags, reserved = struct.unpack_from("<IIIBBBB", raw)
    assert (magic, version, count, sh_degree, bits, flags, reserved) == (0x5053474E, 3, len(ref), 0, 12, 0, 0)
    assert raw[:4] == b"NGSP"
    n = len(ref)
    assert len(raw) == 16 + n * (9 + 1 + 3 + 3 + 4)
    # the first splat's x, read by hand: 24-bit little-endian two's complement with 12 fractional bits
    x = int.from_bytes(raw[16:19], "little", signed=True) / 4096
    y = int.from_bytes(raw[19:22], "little", signed=True) / 4096
    assert abs(x - ref.means[0, 0]) < 1e-3 and abs(y + ref.means[0, 1]) < 1e-3  # right-up-back: y negated
    alpha = raw[16 + 9 * n]
    assert alpha == round(float(ref.opacities[0]) * 255)
    scale0 = raw[16 + 13 * n]
    assert scale0 == round((np.log(ref.scales[0, 0]) + 10) * 16)
    # smallest-three rotation: the 2-bit index of the largest |component| of xyzw sits in the top bits
    word = struct.unpack_from("<I", raw, 16 + 16 * n)[0]
    w, xq, yq, zq = ref.quats[0].astype(np.float64)
    assert word >> 30 == int(np.abs([xq, -yq, -zq, w]).argmax())


def test_spz_keeps_large_scenes_by_coarser_fixed_point():
    rng = np.random.default_rng(1)
    means = rng.uniform(-5000, 5000, (100, 3)).astype(np.float32)
    arrays = SplatArrays(means=means, scales=np.full((100, 3), 0.1, np.float32),
                         quats=np.tile(np.float32([1, 0, 0, 0]), (100, 1)), opacities=np.full(100, 0.5, np.float32),
                         colors=np.full((100, 3), 0.5, np.float32))
    bits = fractional_bits_for(means)
    assert bits < 12 and np.abs(means).max() < 2 ** 23 / 2 ** bits
    back = decode_spz(encode_spz(arrays))
    assert np.abs(back.means - means).max() <= 0.5 / 2 ** bits + 1e-3


def test_splat_round_trip_and_layout(reference):
    _, ref = reference
    data = encode_splat(ref)
    assert len(data) == 32 * len(ref)
    x, y, z, sx, sy, sz = struct.unpack_from("<6f", data)
    assert (x, y, z) == tuple(ref.means[0].tolist()) and (sx, sy) == tuple(ref.scales[0, :2].tolist())
    assert sz < 1e-4
    back = decode_splat(data)
    assert np.array_equal(back.means, ref.means) and np.array_equal(back.scales, ref.scales)
    assert np.abs(back.colors - np.clip(ref.colors, 0, 1)).max() <= 0.5 / 255 + 1e-6
    assert np.abs(back.opacities - ref.opacities).max() <= 0.5 / 255 + 1e-6
    rotation = _rotation_error_deg(back.quats, ref.quats)
    assert rotation.max() < 1.5 and rotation.mean() < 0.5, (rotation.max(), rotation.mean())


def test_the_plane_scene_survives_every_format():
    ply = surfels_to_ply_bytes(voxelized_surfels(camera_pose(0.3, -0.1, yaw=0.4, pitch=-0.2)))
    ref = splat_arrays_from_ply(ply)
    for fmt, decode in (("spz", decode_spz), ("splat", decode_splat)):
        encoded = encode_map(ply, fmt)
        assert encoded.extension == fmt
        back = decode(encoded.body)
        assert len(back) == len(ref)
        normal_error = np.degrees(np.arccos(np.clip((_normals(back.quats) * _normals(ref.quats)).sum(1), -1, 1)))
        assert normal_error.max() < 1.0, fmt
    assert len(encode_map(ply, "spz").body) < len(encode_map(ply, "ply").body) / 4


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown map format"):
        encode_map(b"", "ksplat")
    assert set(FORMATS) == {"ply", "spz", "splat"}
    with pytest.raises(ValueError, match="gzip"):
        decode_spz(b"not gzip at all")
    with pytest.raises(ValueError, match="magic"):
        decode_spz(gzip.compress(b"\0" * 32))
    header = struct.pack("<IIIBBBB", 0x5053474E, 3, 1000, 0, 12, 0, 0)
    with pytest.raises(ValueError, match="truncated"):
        decode_spz(gzip.compress(header + b"\0" * 100))
    with pytest.raises(ValueError, match="multiple of 32"):
        decode_splat(b"\0" * 33)
    with pytest.raises(ValueError, match="PLY"):
        splat_arrays_from_ply(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
