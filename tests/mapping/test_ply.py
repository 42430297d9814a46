import numpy as np
import pytest
import torch
from plyfile import PlyData

from worker.mapping import Surfels
from worker.mapping.ply import SH_C0, read_ply, surfels_from_ply_bytes, surfels_to_ply_bytes, write_ply


def random_surfels(n: int) -> Surfels:
    gen = torch.Generator().manual_seed(0)
    return Surfels(
        means=torch.randn(n, 3, generator=gen),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1),
        scales=torch.rand(n, 2, generator=gen) * 0.1 + 0.001,
        opacities=torch.rand(n, generator=gen) * 0.98 + 0.01,
        colors=torch.rand(n, 3, generator=gen),
        keyframe_ids=torch.arange(n) % 4,
    )


@pytest.mark.parametrize("variant", ["3dgs", "2dgs"])
def test_round_trip(variant, tmp_path):
    s = random_surfels(50)
    path = tmp_path / "map.ply"
    write_ply(path, s, variant=variant, include_keyframe_id=True)
    back = read_ply(path)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.allclose(getattr(back, name), getattr(s, name), atol=1e-5, rtol=1e-5), name
    assert torch.equal(back.keyframe_ids, s.keyframe_ids)


def test_layout_read_by_plyfile():
    s = random_surfels(7)
    data = surfels_to_ply_bytes(s)
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    ply = PlyData.read(__import__("io").BytesIO(data))
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert names == expected
    assert all(p.val_dtype in ("f4", "float32", "float") for p in v.properties)
    assert v.count == 7
    d = v.data
    np.testing.assert_allclose(d["f_dc_0"], (s.colors[:, 0].numpy() - 0.5) / SH_C0, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-d["opacity"])), s.opacities.numpy(), rtol=1e-5)
    np.testing.assert_allclose(np.exp(d["scale_1"]), s.scales[:, 1].numpy(), rtol=1e-5)
    assert np.all(d["scale_2"] < -5)
    np.testing.assert_allclose(d["rot_0"], s.quats[:, 0].numpy(), rtol=1e-6)
    assert np.all(d["nx"] == 0) and np.all(d["f_rest_44"] == 0)
    # 62 floats per record, as raw-struct 3DGS readers expect
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    assert len(data) - header_end == 7 * 62 * 4
    two = PlyData.read(__import__("io").BytesIO(surfels_to_ply_bytes(s, variant="2dgs")))
    assert "scale_2" not in [p.name for p in two["vertex"].properties]


def test_bad_input_raises():
    with pytest.raises(ValueError, match="PLY"):
        surfels_from_ply_bytes(b"definitely not a ply")
    with pytest.raises(ValueError, match="variant"):
        surfels_to_ply_bytes(random_surfels(2), variant="nope")
