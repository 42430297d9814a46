"""The stored map a session runs in, read from its record (`map_id`, `map_version`, `map_mode`), and the new
version an `extend` session makes of it when it finishes."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import redis

from protocol.map_package import MapPackageError, decode_package, encode_package
from protocol.map_store import MapNotFound
from worker.events import MapExtended, MapNotExtended

if TYPE_CHECKING:  # worker.maps imports torch: only a session in a map loads it
    from worker.maps.session_in_map import SessionInMap

log = logging.getLogger(__name__)
MERGE_ATTEMPTS = 5  # another extend session may add a version between our read and our write: merge again


class MapGone(RuntimeError):
    """The map a new session was created in no longer exists."""


def session_in_map(client: redis.Redis, record: dict[str, str], restoring: bool = False) -> SessionInMap | None:
    """The session's stored map (None when it runs in none). A map deleted before the session began is an error
    (`MapGone`); one deleted while it ran leaves a restored session where it was anchored, locating nothing more."""
    map_id = record.get("map_id") or ""
    if not map_id:
        return None
    from worker.maps.session_in_map import SessionInMap
    from worker.maps.store import read_package

    version = int(record.get("map_version") or 0) or None
    mode = record.get("map_mode") or "localize"
    try:
        package = decode_package(read_package(client, map_id, version))
    except MapPackageError as err:
        raise MapGone(f"map {map_id} (version {version}) cannot be read: {err}") from err
    except MapNotFound as err:
        if not restoring:
            raise MapGone(f"map {map_id} (version {version}) no longer exists: {err}") from err
        log.warning("map %s is gone: the session goes on in its world without locating more", map_id)
        package = None
    return SessionInMap.from_package(map_id, version or 0, mode, package)


def extend_stored_map(client: redis.Redis, engine: Any, session_id: str) -> MapExtended | MapNotExtended | None:
    """At the finish of an `extend` session: its map joined to the map's newest version as a new version. The
    event to publish (`map_extended`, or `map_not_extended` with the reason), None for any other session."""
    in_map: SessionInMap | None = getattr(engine, "in_map", None)
    if in_map is None or in_map.mode != "extend":
        return None
    from worker.maps.merge import merge_packages
    from worker.maps.package import build_package
    from worker.maps.store import VersionConflict, add_version, latest_version, read_package

    if not in_map.anchored:
        return MapNotExtended(map_id=in_map.map_id,
                              reason="the session was never relocalized in the map: its frames did not match the map's")
    try:
        own = decode_package(build_package(engine, f"session {session_id}", [session_id]))
    except ValueError as err:
        return MapNotExtended(map_id=in_map.map_id, reason=str(err))
    for _ in range(MERGE_ATTEMPTS):
        try:
            parent = latest_version(client, in_map.map_id)
            merged = merge_packages(decode_package(read_package(client, in_map.map_id, parent)), own, session_id)
            version = add_version(client, in_map.map_id, encode_package(merged), session_id, parent=parent)
        except MapNotFound:
            return MapNotExtended(map_id=in_map.map_id, reason="the map was deleted")
        except VersionConflict:
            continue
        return MapExtended(map_id=in_map.map_id, version=version, keyframes=len(merged.keyframes))
    return MapNotExtended(map_id=in_map.map_id,
                          reason=f"other sessions kept adding versions ({MERGE_ATTEMPTS} attempts)")
