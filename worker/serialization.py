"""msgpack with numpy arrays and torch tensors as raw bytes + dtype + shape. Never pickle.

`pack(obj)` accepts dicts, lists, tuples (packed as lists), str, bytes, numbers, None, numpy arrays and torch
tensors (packed as numpy arrays; bfloat16 is not supported). `unpack(data)` returns numpy arrays for arrays.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

_ARRAY_EXT = 1
_ALLOWED_DTYPES = {
    "bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "float16", "float32", "float64",
}


def _default(obj: Any) -> Any:
    if hasattr(obj, "detach") and hasattr(obj, "cpu"):  # torch.Tensor, without importing torch here
        obj = obj.detach().cpu().numpy()
    if isinstance(obj, np.ndarray):
        arr = np.ascontiguousarray(obj)
        if arr.dtype.name not in _ALLOWED_DTYPES:
            raise TypeError(f"cannot serialize arrays of dtype {arr.dtype}")
        header = msgpack.packb([arr.dtype.name, list(arr.shape)])
        return msgpack.ExtType(_ARRAY_EXT, header + arr.tobytes())
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot serialize {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
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


def pack(obj: Any) -> bytes:
    """Serialize to msgpack bytes."""
    return msgpack.packb(obj, default=_default, use_bin_type=True)


def unpack(data: bytes, max_bytes: int | None = None) -> Any:
    """Deserialize msgpack bytes made by `pack` (raises ValueError on malformed input)."""
    if max_bytes is not None and len(data) > max_bytes:
        raise ValueError(f"message of {len(data)} bytes exceeds the limit of {max_bytes}")
    try:
        return msgpack.unpackb(data, ext_hook=_ext_hook, raw=False, strict_map_key=False)
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError, TypeError) as err:
        raise ValueError(f"malformed msgpack message: {err}") from err
