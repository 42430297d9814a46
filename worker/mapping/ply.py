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
    vertex = _binary_vertices(data)
    names = list(vertex.dtype.names or ()) if vertex is not None else []
    rest = [n for n in names if n.startswith("f_rest_")]
    if "f_dc_0" not in names or len(rest) == wanted:
        return data
    if any(np.any(vertex[n] != 0) for n in rest):  # (3DGS stores them channel-major: no simple truncation)
        raise ValueError("the map has non-zero higher-order SH coefficients; it cannot change SH degree")
    kept = [n for n in names if n not in rest]
    at = kept.index("f_dc_2") + 1
    props = [(n, vertex.dtype[n].str) for n in kept[:at]] + [(f"f_rest_{i}", "<f4") for i in range(wanted)]
    props += [(n, vertex.dtype[n].str) for n in kept[at:]]
    record = np.zeros(len(vertex), dtype=props)
    for name in kept:
        record[name] = vertex[name]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(record)}"]
    header += [f"property {_PLY_TYPE_NAMES[np.dtype(kind).str]} {name}" for name, kind in props]
    return ("\n".join([*header, "end_header"]) + "\n").encode() + record.tobytes()


# PLY scalar type names and their little-endian numpy types (the names plyfile writes first)
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}
_PLY_TYPE_NAMES = {"|i1": "char", "|u1": "uchar", "<i2": "short", "<u2": "ushort", "<i4": "int", "<u4": "uint",
                   "<f4": "float", "<f8": "double"}
_END_HEADER = b"end_header\n"


def _binary_vertices(data: bytes) -> np.ndarray | None:
    """The records of a binary little-endian PLY whose only element is `vertex` with scalar properties (what we
    write), read straight from the bytes; None for any other PLY. plyfile reads in-memory data row by row (5 s for
    50k surfels), this takes milliseconds."""
    end = data.find(_END_HEADER)
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("not a readable PLY file: no 'ply' magic or no end_header")
    lines = data[:end].decode("ascii", "replace").splitlines()
    elements = [line.split() for line in lines if line.startswith("element ")]
    if "format binary_little_endian 1.0" not in lines or len(elements) != 1 or elements[0][1] != "vertex":
        return None
    props = [line.split() for line in lines if line.startswith("property ")]
    if any(len(p) != 3 or p[1] not in _PLY_TYPES for p in props):
        return None  # list properties
    dtype = np.dtype([(p[2], _PLY_TYPES[p[1]]) for p in props])
    count = int(elements[0][2])
    body = memoryview(data)[end + len(_END_HEADER):]
    if len(body) < count * dtype.itemsize:
        raise ValueError(f"PLY data is truncated: {count} vertices need {count * dtype.itemsize} bytes")
    return np.frombuffer(body, dtype=dtype, count=count)


def read_vertex_records(data: bytes) -> np.ndarray:
    """The vertex records of a binary little-endian PLY with one `vertex` element of scalar properties, as a numpy
    structured array viewing `data` (no copy); ValueError for anything else."""
    vertex = _binary_vertices(data)
    if vertex is None:
        raise ValueError("the PLY must be binary little endian with one 'vertex' element of scalar properties")
    return vertex


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
