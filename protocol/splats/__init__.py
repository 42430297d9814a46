"""Gaussian splat files, torch-free (the gateway and the workers both convert maps): the engine's binary Gaussian
PLY read as numpy records (`ply_records`), plain Gaussian arrays (`arrays`), Niantic SPZ (`spz`), antimatter15's
.splat (`splat_file`), and the map in the formats web clients read (`formats.encode_map`)."""

from .arrays import SplatArrays, splat_arrays_from_ply
from .formats import FORMATS, EncodedMap, MapFormat, encode_map
from .ply_records import ply_with_sh_degree, ply_without, read_gaussian_records, read_vertex_records

__all__ = ["FORMATS", "EncodedMap", "MapFormat", "SplatArrays", "encode_map", "ply_with_sh_degree", "ply_without",
           "read_gaussian_records", "read_vertex_records", "splat_arrays_from_ply"]
