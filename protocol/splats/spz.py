"""Niantic's SPZ (version 3), written from its published specification (github.com/nianticlabs/spz, README "File
Format"): one gzip stream of a 16-byte header, then every splat's positions, alphas, colours, scales, rotations
(and SH, none here), attribute by attribute.

Encodings, per splat: position 3 x 24-bit signed fixed point with `fractional_bits`; alpha u8 = sigmoid(opacity)
* 255; colour u8 = f_dc * 0.15 * 255 + 127.5 (the SH DC coefficient, not RGB); scale u8 = (ln(scale) + 10) * 16;
rotation u32 "smallest three" (2 bits: index of the largest |component| of the xyzw quaternion, made positive;
then the other three in order, 1 sign bit + 9 bits of |c| / sqrt(1/2)). SPZ stores right-up-back (OpenGL, three.js)
coordinates: our OpenCV world (right-down-forward) is converted on write (y and z negated, the quaternion
conjugated by the 180-degree turn about x) and back on read.

Version 3 is written rather than 4 (zstd streams behind a 32-byte header): every SPZ reader in use reads 3 (Spark,
Niantic's library, SuperSplat, gsplat.js), and the standard library has gzip but not zstd before Python 3.14.
"""

from __future__ import annotations

import gzip
import struct

import numpy as np

from .arrays import SplatArrays
from .ply_records import SH_C0

MAGIC = 0x5053474E  # "NGSP" little endian
VERSION = 3
HEADER = struct.Struct("<IIIBBBB")  # magic, version, points, sh degree, fractional bits, flags, reserved
COLOR_SCALE = 0.15
MAX_FRACTIONAL_BITS = 12  # the reference library's choice: 0.24 mm steps within +-2 km
_SQRT1_2 = float(np.sqrt(0.5))
_FLIP = np.array([1.0, -1.0, -1.0], dtype=np.float64)  # OpenCV (RDF) <-> SPZ (RUB), its own inverse
_BYTES_PER_POINT = 9 + 1 + 3 + 3 + 4  # degree-0 SH


def fractional_bits_for(means: np.ndarray) -> int:
    """The finest fixed point (<= 12 fractional bits) whose 24-bit range holds every coordinate."""
    extent = float(np.abs(means).max()) if len(means) else 0.0
    bits = MAX_FRACTIONAL_BITS
    while bits > 0 and extent >= (2 ** 23 - 1) / 2 ** bits:
        bits -= 1
    return bits


def _u8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


def _pack_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    q = quats_wxyz[:, [1, 2, 3, 0]].astype(np.float64)  # xyzw, the order SPZ indexes
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    largest = np.abs(q).argmax(axis=1)
    q *= np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    word = largest.astype(np.uint32)
    for i in range(4):
        sign = (q[:, i] < 0).astype(np.uint32)
        magnitude = np.minimum(np.floor(511.0 * np.abs(q[:, i]) / _SQRT1_2 + 0.5), 511).astype(np.uint32)
        packed = (word << np.uint32(10)) | (sign << np.uint32(9)) | magnitude
        word = np.where(largest == i, word, packed)
    return word.astype("<u4")


def _unpack_rotations(words: np.ndarray) -> np.ndarray:
    words = words.astype(np.uint32)
    largest = (words >> np.uint32(30)).astype(np.int64)
    q = np.zeros((len(words), 4), dtype=np.float64)
    rest = words.copy()
    for i in range(3, -1, -1):  # the last stored component sits in the lowest bits
        magnitude = (rest & np.uint32(511)).astype(np.float64) / 511.0 * _SQRT1_2
        sign = np.where(rest & np.uint32(512), -1.0, 1.0)
        stored = largest != i
        q[stored, i] = (sign * magnitude)[stored]
        rest = np.where(stored, rest >> np.uint32(10), rest)
    rows = np.arange(len(words))
    q[rows, largest] = np.sqrt(np.clip(1.0 - (q ** 2).sum(axis=1), 0.0, 1.0))
    return q[:, [3, 0, 1, 2]]  # wxyz


def encode_spz(splats: SplatArrays, fractional_bits: int | None = None) -> bytes:
    """The splats as an SPZ v3 file (degree-0 SH: 20 bytes a splat before gzip)."""
    n = len(splats)
    bits = fractional_bits_for(splats.means) if fractional_bits is None else fractional_bits
    fixed = np.rint(splats.means.astype(np.float64) * _FLIP * 2 ** bits)
    fixed = np.clip(fixed, -(2 ** 23), 2 ** 23 - 1).astype("<i4")
    positions = fixed.view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    alphas = _u8(splats.opacities.astype(np.float64) * 255.0)
    colors = _u8(splats.f_dc.astype(np.float64) * (COLOR_SCALE * 255.0) + 127.5)
    log_scales = np.log(np.maximum(splats.scales.astype(np.float64), 1e-30))
    scales = _u8((log_scales + 10.0) * 16.0)
    quats = splats.quats.astype(np.float64).copy()
    quats[:, 1:] *= _FLIP
    rotations = _pack_rotations(quats)
    header = HEADER.pack(MAGIC, VERSION, n, 0, bits, 0, 0)
    body = b"".join(a.tobytes() for a in (positions, alphas, colors, scales, rotations))
    return gzip.compress(header + body, compresslevel=6, mtime=0)


def decode_spz(data: bytes) -> SplatArrays:
    """Read an SPZ file of version 2 or 3 (any SH degree; the SH beyond degree 0 is skipped)."""
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError) as err:
        raise ValueError(f"not an SPZ file (gzip): {err}") from err
    if len(raw) < HEADER.size:
        raise ValueError("SPZ stream shorter than its header")
    magic, version, n, sh_degree, bits, _flags, _ = HEADER.unpack_from(raw)
    if magic != MAGIC:
        raise ValueError(f"not an SPZ file: magic {magic:#x}")
    if version not in (2, 3):
        raise ValueError(f"SPZ version {version} is not supported here (2 and 3 are)")
    if sh_degree > 4:
        raise ValueError(f"SPZ SH degree {sh_degree} is out of range")
    rotation_bytes = 4 if version >= 3 else 3
    sh_bytes = 3 * ((sh_degree + 1) ** 2 - 1)
    need = HEADER.size + n * (9 + 1 + 3 + 3 + rotation_bytes + sh_bytes)
    if len(raw) < need:
        raise ValueError(f"SPZ data truncated: {n} points need {need} bytes, got {len(raw)}")
    at = HEADER.size

    def take(count: int) -> np.ndarray:
        nonlocal at
        chunk = np.frombuffer(raw, dtype=np.uint8, count=count, offset=at)
        at += count
        return chunk

    pos = take(9 * n).reshape(n, 3, 3).astype(np.int32)
    fixed = pos[:, :, 0] | (pos[:, :, 1] << 8) | (pos[:, :, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float64) / 2 ** bits * _FLIP
    opacities = take(n).astype(np.float64) / 255.0
    f_dc = (take(3 * n).reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE
    scales = np.exp(take(3 * n).reshape(n, 3).astype(np.float64) / 16.0 - 10.0)
    if version >= 3:
        quats = _unpack_rotations(take(4 * n).reshape(n, 4).copy().view("<u4")[:, 0])
    else:  # xyz as bytes, w rebuilt positive
        xyz = take(3 * n).reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.clip(1.0 - (xyz ** 2).sum(axis=1), 0.0, 1.0))
        quats = np.concatenate([w[:, None], xyz], axis=1)
    quats[:, 1:] *= _FLIP
    return SplatArrays(means=means.astype(np.float32), scales=scales.astype(np.float32),
                       quats=quats.astype(np.float32), opacities=opacities.astype(np.float32),
                       colors=(0.5 + SH_C0 * f_dc).astype(np.float32))
