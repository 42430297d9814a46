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

from .surfels import Surfels

SH_C0 = 0.28209479177387814
NUM_F_REST = 45
FLAT_LOG_SCALE = -10.0  # scale_2 of the 3dgs variant: a finite, tiny thickness
_EPS = 1e-7
VARIANTS = ("3dgs", "2dgs")


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


def sh_rest_count(degree: int) -> int:
    """f_rest coefficients of spherical harmonics up to `degree` (0..3): 3 colour channels x ((degree + 1)^2 - 1)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be within 0..3, got {degree}")
    return 3 * ((degree + 1) ** 2 - 1)


def ply_with_sh_degree(data: bytes, degree: int) -> bytes:
    """The Gaussian PLY `data` with the f_rest properties of SH `degree`: 0 drops them (our surfels keep their colour
    in f_dc alone, f_rest is all zeros: 68 instead of 248 bytes a surfel), 3 gives the 45 that fixed-record 3DGS
    readers expect. A PLY without f_dc (not a Gaussian map) is returned unchanged."""
    wanted = sh_rest_count(degree)
    try:
        vertex = PlyData.read(io.BytesIO(data))["vertex"].data
    except Exception as err:  # plyfile raises several types on malformed input
        raise ValueError(f"not a readable PLY file: {err}") from err
    names = list(vertex.dtype.names or ())
    rest = [n for n in names if n.startswith("f_rest_")]
    if "f_dc_0" not in names or len(rest) == wanted:
        return data
    if any(np.any(vertex[n] != 0) for n in rest):  # (3DGS stores them channel-major: no simple truncation)
        raise ValueError("the map has non-zero higher-order SH coefficients; it cannot change SH degree")
    before = [(n, vertex.dtype[n].str) for n in names[:names.index("f_dc_2") + 1]]
    after = [(n, vertex.dtype[n].str) for n in names if n not in rest and (n, vertex.dtype[n].str) not in before]
    props = before + [(f"f_rest_{i}", "<f4") for i in range(wanted)] + after
    record = np.zeros(len(vertex), dtype=props)
    for name in record.dtype.names:
        if name in names and not name.startswith("f_rest_"):
            record[name] = vertex[name]
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(record, "vertex")], text=False, byte_order="<").write(buffer)
    return buffer.getvalue()


def surfels_from_ply_bytes(data: bytes) -> Surfels:
    """Surfels from a PLY file in the 3DGS or 2DGS layout (extra properties are ignored; f_rest is dropped)."""
    try:
        ply = PlyData.read(io.BytesIO(data))
        vertex = ply["vertex"].data
    except Exception as err:  # plyfile raises several types on malformed input
        raise ValueError(f"not a readable PLY file: {err}") from err
    names = set(vertex.dtype.names or ())
    required = {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                "rot_0", "rot_1", "rot_2", "rot_3"}
    missing = sorted(required - names)
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
