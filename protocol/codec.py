"""The msgpack codec of every message and stored record: numpy arrays (and torch tensors, recognised without
importing torch) as raw bytes + dtype + shape. Never pickle.

`pack(obj)` accepts dicts, lists, tuples (packed as lists), str, bytes, numbers, None, numpy arrays and torch
tensors (packed as numpy arrays; bfloat16 is not supported). `unpack(data)` returns numpy arrays for arrays.

`pack(obj, external=store)` keeps large arrays out of the bytes: each array of at least `EXTERNAL_MIN_BYTES` is
packed as a reference to its content digest, and its packed form goes to `store[digest]`; `unpack(data,
external=store)` resolves them. A state whose large arrays do not change between two packs (keyframe images and
depth) then names the same digests, and a store that holds them already needs only the new ones (incremental
snapshots, worker.runtime.snapshots).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from functools import partial
from typing import Any

import msgpack
import numpy as np

_ARRAY_EXT = 1
_EXTERNAL_EXT = 2  # an array kept outside the bytes: its content digest (hex, ASCII)
EXTERNAL_MIN_BYTES = 1 << 14
_ALLOWED_DTYPES = {
    "bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "float16", "float32", "float64",
}


def _default(obj: Any, external: dict[str, bytes] | None = None) -> Any:
    if hasattr(obj, "detach") and hasattr(obj, "cpu"):  # torch.Tensor, without importing torch here
        obj = obj.detach().cpu().numpy()
    if isinstance(obj, np.ndarray):
        arr = np.ascontiguousarray(obj)
        if arr.dtype.name not in _ALLOWED_DTYPES:
            raise TypeError(f"cannot serialize arrays of dtype {arr.dtype}")
        header = msgpack.packb([arr.dtype.name, list(arr.shape)])
        payload = header + arr.tobytes()
        if external is not None and arr.nbytes >= EXTERNAL_MIN_BYTES:
            digest = hashlib.blake2b(payload, digest_size=16).hexdigest()
            external[digest] = payload
            return msgpack.ExtType(_EXTERNAL_EXT, digest.encode())
        return msgpack.ExtType(_ARRAY_EXT, payload)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot serialize {type(obj).__name__}")


def _ext_hook(code: int, data: bytes, external: Mapping[str, bytes] | None = None) -> Any:
    if code == _EXTERNAL_EXT and external is not None:
        digest = data.decode("ascii", errors="replace")
        payload = external.get(digest)
        if payload is None:
            raise ValueError(f"the data refers to array {digest}, which is missing")
        return _ext_hook(_ARRAY_EXT, payload)
    if code != _ARRAY_EXT:
        raise ValueError(f"unknown msgpack extension type {code}")
    unpacker = msgpack.Unpacker(raw=False)
    unpacker.feed(data)
    dtype_name, shape = unpacker.unpack()
    if dtype_name not in _ALLOWED_DTYPES:
        raise ValueError(f"refusing array of dtype {dtype_name!r}")
    offset = unpacker.tell()
    count = int(np.prod(shape)) if shape else 1
    dtype = np.dtype(dtype_name)
    if len(data) - offset != count * dtype.itemsize:
        raise ValueError("array payload does not match its shape")
    return np.frombuffer(data, dtype=dtype, offset=offset, count=count).reshape(shape).copy()


def pack(obj: Any, external: dict[str, bytes] | None = None) -> bytes:
    """Serialize to msgpack bytes; with `external`, large arrays go there by digest (see the module docstring)."""
    return msgpack.packb(obj, default=_default if external is None else partial(_default, external=external),
                         use_bin_type=True)


def unpack(data: bytes, max_bytes: int | None = None, external: Mapping[str, bytes] | None = None) -> Any:
    """Deserialize msgpack bytes made by `pack` (raises ValueError on malformed input); `external` holds the
    arrays a `pack(..., external=...)` kept out (a reference without it is malformed input)."""
    if max_bytes is not None and len(data) > max_bytes:
        raise ValueError(f"message of {len(data)} bytes exceeds the limit of {max_bytes}")
    try:
        return msgpack.unpackb(data, ext_hook=_ext_hook if external is None else partial(_ext_hook, external=external),
                               raw=False, strict_map_key=False)
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError, TypeError) as err:
        raise ValueError(f"malformed msgpack message: {err}") from err
