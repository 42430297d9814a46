"""The map in the formats web clients read: the PLY the engine exports, converted to SPZ or .splat."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from .arrays import splat_arrays_from_ply
from .ply_records import ply_with_sh_degree
from .splat_file import encode_splat
from .spz import encode_spz

MapFormat = Literal["ply", "spz", "splat"]
FORMATS: tuple[str, ...] = get_args(MapFormat)


@dataclass(frozen=True)
class EncodedMap:
    """A map file: its bytes, media type and file extension."""

    body: bytes
    content_type: str
    extension: str


def encode_map(ply: bytes, fmt: str = "ply", sh_degree: int = 0) -> EncodedMap:
    """The map `ply` (a Gaussian PLY) in format `fmt`; `sh_degree` applies to PLY output only (SPZ and .splat
    carry the degree-0 colour the map has)."""
    if fmt == "ply":
        return EncodedMap(ply_with_sh_degree(ply, sh_degree), "application/octet-stream", "ply")
    if fmt == "spz":
        return EncodedMap(encode_spz(splat_arrays_from_ply(ply)), "application/octet-stream", "spz")
    if fmt == "splat":
        return EncodedMap(encode_splat(splat_arrays_from_ply(ply)), "application/octet-stream", "splat")
    raise ValueError(f"unknown map format {fmt!r}; choose one of {', '.join(FORMATS)}")
