"""The map PLY served to viewers carries no always-zero SH coefficients unless asked for (`ply_with_sh_degree`)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from mapping_scene import camera_pose, voxelized_surfels
from plyfile import PlyData, PlyElement

from worker.mapping.ply import ply_with_sh_degree, sh_rest_count, surfels_from_ply_bytes, surfels_to_ply_bytes

HEADER_SLACK = 2048  # a PLY header is well under this


def _names(data: bytes) -> list[str]:
    return [p.name for p in PlyData.read(io.BytesIO(data))["vertex"].properties]


@pytest.mark.parametrize("variant, floats", [("3dgs", 17), ("2dgs", 16)])
def test_degree_0_drops_f_rest_and_keeps_every_surfel_exactly(variant, floats):
    surfels = voxelized_surfels(camera_pose(), keyframe_id=3)
    full = surfels_to_ply_bytes(surfels, variant, include_keyframe_id=True)
    compact = ply_with_sh_degree(full, 0)
    assert not any(n.startswith("f_rest_") for n in _names(compact))
    assert _names(compact) == [n for n in _names(full) if not n.startswith("f_rest_")]
    n = len(surfels)
    assert len(compact) - n * (floats * 4 + 4) < HEADER_SLACK  # + the int32 keyframe id
    assert len(full) - len(compact) >= n * 45 * 4
    back, reference = surfels_from_ply_bytes(compact), surfels_from_ply_bytes(full)
    for name in ("means", "quats", "scales", "opacities", "colors", "keyframe_ids"):
        assert torch.equal(getattr(back, name), getattr(reference, name)), name


def test_degree_3_restores_the_fixed_62_float_records():
    surfels = voxelized_surfels(camera_pose())
    full = surfels_to_ply_bytes(surfels)
    again = ply_with_sh_degree(ply_with_sh_degree(full, 0), 3)
    assert again == full  # byte for byte: the same layout and values
    assert ply_with_sh_degree(full, 3) is full  # nothing to do


def test_degrees_and_refusals():
    assert [sh_rest_count(d) for d in range(4)] == [0, 9, 24, 45]
    with pytest.raises(ValueError):
        sh_rest_count(4)
    ascii_points = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n"
    assert ply_with_sh_degree(ascii_points, 0) == ascii_points  # not a Gaussian map: untouched
    with pytest.raises(ValueError, match="PLY"):
        ply_with_sh_degree(b"not a ply", 0)


def test_non_zero_higher_order_coefficients_are_not_silently_dropped():
    full = surfels_to_ply_bytes(voxelized_surfels(camera_pose()))
    vertex = PlyData.read(io.BytesIO(full))["vertex"].data.copy()
    vertex["f_rest_7"][0] = 0.5
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(buffer)
    with pytest.raises(ValueError, match="non-zero"):
        ply_with_sh_degree(buffer.getvalue(), 0)
    assert np.count_nonzero(vertex["f_rest_7"]) == 1
