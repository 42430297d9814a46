"""PLY export/import of surfels in the 3DGS/2DGS layout (binary little endian, one `vertex` element).

Properties, in order: x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0 scale_1 [scale_2] rot_0..3
[keyframe_id]. Values are pre-activation as the official trainers store them: logit opacity, log scales, wxyz
rotation, degree-0 SH colour f_dc = (rgb - 0.5) / C0; normals and f_rest are zeros. The "3dgs" variant adds
scale_2 = log(tiny) so 3DGS viewers (fixed 62-float records) load it; "2dgs" is the official 2DGS layout with two
scales. `keyframe_id` (int32) is optional and off by default because raw-struct readers such as SIBR expect no
extra properties.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from protocol.splats.ply_records import (  # the torch-free part, re-exported (__all__)
    FLAT_LOG_SCALE,
    GAUSSIAN_PROPERTIES,
    NUM_F_REST,
    SH_C0,
    binary_vertices,
    ply_with_sh_degree,
    read_vertex_records,
    sh_rest_count,
)

from .surfels import Surfels

_EPS = 1e-7
VARIANTS = ("3dgs", "2dgs")
__all__ = ["FLAT_LOG_SCALE", "NUM_F_REST", "SH_C0", "VARIANTS", "ply_with_sh_degree", "read_ply", "read_vertex_records",
           "sh_rest_count", "surfels_from_ply_bytes", "surfels_to_ply_bytes", "write_ply"]


def _property_names(variant: str, include_keyframe_id: bool) -> list[tuple[str, str]]:
    if variant not in VARIANTS:
        raise ValueError(f"unknown PLY variant {variant!r}; expected one of {VARIANTS}")
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(NUM_F_REST)]
    names += ["opacity", "scale_0", "scale_1"] + (["scale_2"] if variant == "3dgs" else [])
    names += ["rot_0", "rot_1", "rot_2", "rot_3"]
    props = [(n, "<f4") for n in names]
    if include_keyframe_id:
        props.append(("keyframe_id", "<i4"))
    return props


def surfels_to_ply_bytes(surfels: Surfels, variant: str = "3dgs", include_keyframe_id: bool = False) -> bytes:
    """The surfels as a binary little-endian PLY file."""
    props = _property_names(variant, include_keyframe_id)
    s = surfels.detach().to("cpu", torch.float64)
    n = len(s)
    record = np.zeros(n, dtype=props)
    means = s.means.numpy()
    record["x"], record["y"], record["z"] = means[:, 0], means[:, 1], means[:, 2]
    f_dc = ((s.colors - 0.5) / SH_C0).numpy()
    for c in range(3):
        record[f"f_dc_{c}"] = f_dc[:, c]
    record["opacity"] = torch.logit(s.opacities.clamp(_EPS, 1 - _EPS)).numpy()
    log_scales = torch.log(s.scales.clamp_min(1e-12)).numpy()
    record["scale_0"], record["scale_1"] = log_scales[:, 0], log_scales[:, 1]
    if variant == "3dgs":
        record["scale_2"] = FLAT_LOG_SCALE
    quats = s.quats.numpy()
    for i in range(4):
        record[f"rot_{i}"] = quats[:, i]
    if include_keyframe_id:
        record["keyframe_id"] = s.keyframe_ids.numpy().astype(np.int32)
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(record, "vertex")], text=False, byte_order="<").write(buffer)
    return buffer.getvalue()


def surfels_from_ply_bytes(data: bytes) -> Surfels:
    """Surfels from a PLY file in the 3DGS or 2DGS layout (extra properties are ignored; f_rest is dropped). The
    binary layout the engine writes is read with numpy straight from the bytes, any other PLY with plyfile."""
    try:
        vertex = binary_vertices(data)
        if vertex is None:
            vertex = PlyData.read(io.BytesIO(data))["vertex"].data
    except Exception as err:  # plyfile raises several types on malformed input
        raise ValueError(f"not a readable PLY file: {err}") from err
    names = set(vertex.dtype.names or ())
    missing = sorted(GAUSSIAN_PROPERTIES - names)
    if missing:
        raise ValueError(f"PLY vertex element lacks properties {missing}")

    def column(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float64) for k in keys], axis=-1))

    quats = column("rot_0", "rot_1", "rot_2", "rot_3")
    quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = quats.shape[0]
    keyframe_ids = (torch.from_numpy(np.asarray(vertex["keyframe_id"], dtype=np.int64)) if "keyframe_id" in names
                    else torch.full((n,), -1, dtype=torch.int64))
    return Surfels(
        means=column("x", "y", "z").float(),
        quats=quats.float(),
        scales=torch.exp(column("scale_0", "scale_1")).float(),
        opacities=torch.sigmoid(column("opacity")[:, 0]).float(),
        colors=(0.5 + SH_C0 * column("f_dc_0", "f_dc_1", "f_dc_2")).float(),
        keyframe_ids=keyframe_ids,
    )


def write_ply(path: str | Path, surfels: Surfels, variant: str = "3dgs", include_keyframe_id: bool = False) -> None:
    """Write `surfels_to_ply_bytes` to a file."""
    Path(path).write_bytes(surfels_to_ply_bytes(surfels, variant, include_keyframe_id))


def read_ply(path: str | Path) -> Surfels:
    """Read a 3DGS/2DGS PLY file."""
    return surfels_from_ply_bytes(Path(path).read_bytes())
