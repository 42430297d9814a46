"""Gaussian PLY files as numpy records, torch-free: the reader the format converters and the gateway use, and the
rewrites of a file's properties (SH degree, extra columns).

The layout is the engine's (worker.mapping.ply): binary little endian, one `vertex` element of scalar properties
x y z nx ny nz f_dc_0..2 [f_rest_..] opacity scale_0 scale_1 [scale_2] rot_0..3 [keyframe_id], values
pre-activation as the 3DGS trainers store them (logit opacity, log scales, wxyz rotation, f_dc = (rgb - 0.5) / C0).
"""

from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814
NUM_F_REST = 45
FLAT_LOG_SCALE = -10.0  # scale_2 of the 3dgs variant: a finite, tiny thickness
GAUSSIAN_PROPERTIES = frozenset({"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                                 "rot_0", "rot_1", "rot_2", "rot_3"})
"""What a PLY must carry to be read as Gaussians."""

# PLY scalar type names and their little-endian numpy types (the names plyfile writes first)
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}
_PLY_TYPE_NAMES = {"|i1": "char", "|u1": "uchar", "<i2": "short", "<u2": "ushort", "<i4": "int", "<u4": "uint",
                   "<f4": "float", "<f8": "double"}
_END_HEADER = b"end_header\n"


def binary_vertices(data: bytes) -> np.ndarray | None:
    """The records of a binary little-endian PLY whose only element is `vertex` with scalar properties (what the
    engine writes), read straight from the bytes (a view, no copy); None for any other PLY; ValueError for bytes
    that are no readable PLY. plyfile reads in-memory data row by row (5 s for 50k surfels), this takes
    milliseconds."""
    end = data.find(_END_HEADER)
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("not a readable PLY file: no 'ply' magic or no end_header")
    lines = data[:end].decode("ascii", "replace").splitlines()
    elements = [line.split() for line in lines if line.startswith("element ")]
    if "format binary_little_endian 1.0" not in lines or len(elements) != 1 or elements[0][1:2] != ["vertex"]:
        return None
    props = [line.split() for line in lines if line.startswith("property ")]
    if any(len(p) != 3 or p[1] not in _PLY_TYPES for p in props):
        return None  # list properties
    if len(elements[0]) != 3 or not elements[0][2].isdigit():
        raise ValueError(f"PLY header names no vertex count: {' '.join(elements[0])!r}")
    names = [p[2] for p in props]
    if not names or len(set(names)) != len(names):
        raise ValueError("PLY vertex element has no properties, or one twice")
    dtype = np.dtype([(name, _PLY_TYPES[kind]) for _, kind, name in props])
    count = int(elements[0][2])
    body = memoryview(data)[end + len(_END_HEADER):]
    if len(body) < count * dtype.itemsize:
        raise ValueError(f"PLY data is truncated: {count} vertices need {count * dtype.itemsize} bytes")
    return np.frombuffer(body, dtype=dtype, count=count)


def read_vertex_records(data: bytes) -> np.ndarray:
    """The vertex records of a binary little-endian PLY with one `vertex` element of scalar properties, as a numpy
    structured array viewing `data` (no copy); ValueError for anything else."""
    vertex = binary_vertices(data)
    if vertex is None:
        raise ValueError("the PLY must be binary little endian with one 'vertex' element of scalar properties")
    return vertex


def read_gaussian_records(data: bytes) -> np.ndarray:
    """`read_vertex_records`, checked to carry every property of a Gaussian (GAUSSIAN_PROPERTIES)."""
    vertex = read_vertex_records(data)
    missing = sorted(GAUSSIAN_PROPERTIES - set(vertex.dtype.names or ()))
    if missing:
        raise ValueError(f"PLY vertex element lacks properties {missing}")
    return vertex


def write_vertex_records(record: np.ndarray) -> bytes:
    """A binary little-endian PLY of one `vertex` element holding the structured array `record`."""
    names = record.dtype.names or ()
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(record)}"]
    header += [f"property {_PLY_TYPE_NAMES[record.dtype[name].str]} {name}" for name in names]
    return ("\n".join([*header, "end_header"]) + "\n").encode() + np.ascontiguousarray(record).tobytes()


def _rewritten(vertex: np.ndarray, props: list[tuple[str, str]]) -> bytes:
    """The records of `vertex` with the properties `props` ((name, numpy type) in order; new ones zero)."""
    record = np.zeros(len(vertex), dtype=props)
    for name, _ in props:
        if name in (vertex.dtype.names or ()):
            record[name] = vertex[name]
    return write_vertex_records(record)


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
    vertex = binary_vertices(data)
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
    return _rewritten(vertex, props)


def ply_without(data: bytes, *names: str) -> bytes:
    """The binary PLY `data` without the properties `names` (e.g. the engine's `keyframe_id`, which raw-struct
    readers such as SIBR do not expect); unchanged when it has none of them."""
    vertex = read_vertex_records(data)
    present = vertex.dtype.names or ()
    if not set(names) & set(present):
        return data
    return _rewritten(vertex, [(n, vertex.dtype[n].str) for n in present if n not in names])
