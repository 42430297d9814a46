"""Maps in Redis for the workers (sync redis): a map's package by version, and new versions of a map (an `extend`
session at finish). The key layout is protocol.keys', the scripts protocol.map_store's (shared with the gateway)."""

from __future__ import annotations

from datetime import UTC, datetime

import redis

from protocol import keys
from protocol.map_package import package_meta
from protocol.map_store import ADD_VERSION, MapNotFound, version_args


class VersionConflict(RuntimeError):
    """Another version was added since the one a new version was made from."""


def latest_version(client: redis.Redis, map_id: str) -> int:
    """The number of the map's newest version; MapNotFound when the map does not exist."""
    latest = client.hget(keys.map_record(map_id), "latest")
    if latest is None or int(latest) < 1:
        raise MapNotFound(f"map {map_id} not found")
    return int(latest)


def read_package(client: redis.Redis, map_id: str, version: int | None = None) -> bytes:
    """The package bytes of version `version` of a map (None: its latest); MapNotFound when the map or that
    version does not exist (a deleted map's are gone)."""
    if version is None:
        version = latest_version(client, map_id)
    data = client.hget(keys.map_packages(map_id), str(int(version)))
    if data is None:
        raise MapNotFound(f"map {map_id} has no version {version}")
    return data


def add_version(client: redis.Redis, map_id: str, package: bytes, session_id: str, parent: int | None = None) -> int:
    """Store `package` as the next version of an existing map, made by `session_id`; its number. The old versions
    stay until the map is deleted. MapPackageError when the package is corrupt, MapNotFound when the map is gone,
    VersionConflict when `parent` (the version it was made from) is no longer the newest."""
    meta = package_meta(package)
    created = datetime.now(UTC).isoformat(timespec="milliseconds")
    version = int(client.register_script(ADD_VERSION)(keys=[keys.map_record(map_id), keys.map_packages(map_id)],
                                                      args=version_args(package, meta, session_id, created,
                                                                        parent)))
    if version == -2:
        raise VersionConflict(f"map {map_id} has a version newer than {parent}")
    if version < 0:
        raise MapNotFound(f"map {map_id} not found (deleted?)")
    return version
