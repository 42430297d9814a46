"""How maps are kept in Redis, written once for the gateway (service.maps, redis.asyncio) and the workers
(worker.maps.store, redis): the Lua scripts that change a map's keys (protocol.keys: record, packages, sessions, all
in one hash slot) and the names of the record's fields. Nothing here talks to Redis itself.
"""

from __future__ import annotations

import json
from typing import Any, Literal, get_args

MapStatus = Literal["ready"]
MAP_STATUSES: tuple[str, ...] = get_args(MapStatus)
SessionRole = Literal["built", "used"]
MapMode = Literal["localize", "extend"]
MAP_MODES: tuple[str, ...] = get_args(MapMode)

# A new version of an existing map, atomically: the next version number, its package, its fields in the record, and
# `latest`. KEYS: record, packages. ARGV: package, meta JSON, size, created_at, session id, the version it was made
# from ('' for any). Returns the version, -1 when the map is gone (deleted meanwhile), -2 when the version it was
# made from is no longer the newest (nothing is written either way).
ADD_VERSION = """
if redis.call('EXISTS', KEYS[1]) == 0 then return -1 end
if ARGV[6] ~= '' and redis.call('HGET', KEYS[1], 'latest') ~= ARGV[6] then return -2 end
local v = redis.call('HINCRBY', KEYS[1], 'versions', 1)
redis.call('HSET', KEYS[2], v, ARGV[1])
local p = 'v' .. v .. '.'
redis.call('HSET', KEYS[1], 'latest', v, 'updated_at', ARGV[4], p .. 'meta', ARGV[2], p .. 'size', ARGV[3],
           p .. 'created_at', ARGV[4], p .. 'session_id', ARGV[5])
return v
"""

# A session's part in a map, unless the map is gone. KEYS: record, sessions. ARGV: session id, entry JSON. 1 or 0.
ADD_SESSION = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
redis.call('HSET', KEYS[2], ARGV[1], ARGV[2])
return 1
"""


class MapNotFound(LookupError):
    """No such map, or no such version of it."""


def version_field(version: int, name: str) -> str:
    """The record field `name` (meta, size, created_at, session_id) of a version."""
    return f"v{version}.{name}"


def version_args(package: bytes, meta: dict[str, Any], session_id: str, created_at: str,
                 parent: int | None = None) -> list[Any]:
    """ADD_VERSION's ARGV (`parent`: the version the package was made from, None: any)."""
    return [package, json.dumps(meta), len(package), created_at, session_id, "" if parent is None else str(parent)]


def session_entry(role: SessionRole, map_mode: str | None, at: str) -> str:
    """A `sessions` hash value: how a session took part in a map."""
    return json.dumps({"role": role, "map_mode": map_mode, "at": at})
