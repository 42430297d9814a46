"""JSON schemas of the typed WebSocket messages (`protocol.messages`), for openapi.yaml's `x-websocket`."""

from __future__ import annotations

import types
import typing
from dataclasses import MISSING, fields
from typing import Any, Literal, get_args, get_origin, get_type_hints

from protocol.messages import Message

_SCALARS = {int: {"type": "integer"}, float: {"type": "number"}, bool: {"type": "boolean"}, str: {"type": "string"},
            bytes: {"type": "string", "format": "binary"}}


def type_schema(hint: Any) -> dict[str, Any]:
    """The JSON schema of a field's type hint (None dropped from unions: absent means unset)."""
    origin = get_origin(hint)
    if origin is Literal:
        values = list(get_args(hint))
        if len(values) == 1:
            return {"const": values[0]}
        return {"type": "string", "enum": values} if all(isinstance(v, str) for v in values) else {"enum": values}
    if origin in (typing.Union, types.UnionType):
        options = [type_schema(arg) for arg in get_args(hint) if arg is not type(None)]
        return options[0] if len(options) == 1 else {"oneOf": options}
    if origin is list:
        (item,) = get_args(hint)
        return {"type": "array", "items": type_schema(item)}
    if origin is dict or hint is dict:
        return {"type": "object"}
    if hint in _SCALARS:
        return dict(_SCALARS[hint])
    raise TypeError(f"no JSON schema for {hint!r}")


def message_schema(kind: type[Message], with_description: bool = True) -> dict[str, Any]:
    """{type: object, properties, required?, additionalProperties?, description?} of one message class."""
    hints = get_type_hints(kind)
    properties: dict[str, Any] = {"type": {"const": kind.TYPE}}
    required = ["type"]
    for item in fields(kind):
        schema = {**type_schema(hints[item.name]), **item.metadata.get("schema", {})}
        if item.metadata.get("doc"):
            schema["description"] = item.metadata["doc"]
        properties[item.name] = schema
        if item.default is MISSING and item.default_factory is MISSING:
            required.append(item.name)
    out: dict[str, Any] = {"type": "object", "required": required, "properties": properties}
    if kind.OPEN:
        out["additionalProperties"] = True
    if with_description and kind.DOC:
        out["description"] = kind.DOC
    return out

