"""The gateway's map store: map records, their packages by version and the sessions that built or used them, in
Redis (the key layout is protocol.keys', the scripts protocol.map_store's, shared with the workers; redis.asyncio).
"""

from __future__ import annotations

import json
import uuid
from typing import Any

import redis.asyncio as aioredis

from protocol import keys
from protocol.map_store import ADD_SESSION, ADD_VERSION, MapNotFound, session_entry, version_args, version_field
from service.paging import index_member, index_page
from service.registry import now_iso
from worker.runtime.connection import is_cluster


class MapStore:
    """Maps in Redis, for one gateway process."""

    def __init__(self, client: aioredis.Redis) -> None:
        self.client = client
        self.cluster = is_cluster(client)
        self._add_version = client.register_script(ADD_VERSION)
        self._add_session = client.register_script(ADD_SESSION)

    async def create(self, package: bytes, meta: dict[str, Any], name: str, owner: str,
                     built_by: list[str]) -> dict[str, str]:
        """A new map holding `package` (checked by the caller; `meta` its metadata) as version 1, owned by the key
        hash `owner`, built by the sessions `built_by` (none for an upload); its raw record."""
        map_id = uuid.uuid4().hex
        created = now_iso()
        member = index_member(map_id)
        await self.client.hset(keys.map_record(map_id), mapping={
            "id": map_id, "name": name, "owner": owner, "status": "ready", "created_at": created,
            "updated_at": created, "latest": 0, "versions": 0, "index_member": member})
        await self._add_version(keys=[keys.map_record(map_id), keys.map_packages(map_id)],
                                args=version_args(package, meta, built_by[0] if built_by else "", created))
        for session_id in built_by:
            await self._add_session(keys=[keys.map_record(map_id), keys.map_sessions(map_id)],
                                    args=[session_id, session_entry("built", None, created)])
        await self.client.zadd(keys.MAPS_INDEX, {member: 0})  # last: a listed map always has its version
        record = await self.get_raw(map_id)
        if record is None:  # deleted by another request between these calls
            raise MapNotFound(f"map {map_id} was deleted while it was created")
        return record

    async def get_raw(self, map_id: str) -> dict[str, str] | None:
        raw = await self.client.hgetall(keys.map_record(map_id))
        if not raw or b"id" not in raw or int(raw.get(b"latest") or 0) < 1:
            return None  # absent, or a map whose creation did not get as far as its first version
        return {k.decode(): v.decode() for k, v in raw.items()}

    async def list(self, owner: str | None, limit: int, cursor: str | None) -> tuple[list[dict[str, str]], str | None]:
        """Newest first, the maps of the key hash `owner` (None: every map); paged as sessions are."""
        return await index_page(self.client, keys.MAPS_INDEX, keys.map_record,
                                lambda r: int(r.get("latest") or 0) > 0 and (owner is None or r.get("owner") == owner),
                                limit, cursor)

    async def package(self, map_id: str, version: int) -> bytes:
        """The package bytes of a version; MapNotFound when it is not kept."""
        data = await self.client.hget(keys.map_packages(map_id), str(version))
        if data is None:
            raise MapNotFound(f"map {map_id} has no version {version}")
        return data

    async def add_session(self, map_id: str, session_id: str, map_mode: str) -> bool:
        """Record that a session was created in the map (False: the map is gone)."""
        entry = session_entry("used", map_mode, now_iso())
        return bool(await self._add_session(keys=[keys.map_record(map_id), keys.map_sessions(map_id)],
                                            args=[session_id, entry]))

    async def sessions(self, map_id: str) -> list[dict[str, Any]]:
        """The sessions that built or used the map, oldest first, with their status now (None: deleted)."""
        raw = await self.client.hgetall(keys.map_sessions(map_id))
        entries = sorted(((k.decode(), json.loads(v)) for k, v in raw.items()), key=lambda item: item[1]["at"])
        pipe = self.client.pipeline(transaction=False)
        for session_id, _ in entries:
            pipe.hget(keys.session(session_id), "status")
        statuses = await pipe.execute() if entries else []
        return [{"id": session_id, "role": entry["role"], "map_mode": entry.get("map_mode"),
                 "status": status.decode() if status else None}
                for (session_id, entry), status in zip(entries, statuses)]

    async def delete(self, map_id: str, record: dict[str, str]) -> None:
        """Every version and key of the map (sessions running in it keep the copy they loaded)."""
        await self.client.execute_command("DEL", *keys.all_map_keys(map_id))  # one hash slot: one command
        if record.get("index_member"):
            await self.client.zrem(keys.MAPS_INDEX, record["index_member"])


def versions(record: dict[str, str]) -> list[dict[str, Any]]:
    """The API form of every version a map record lists, oldest first."""
    out = []
    for version in range(1, int(record.get("versions") or 0) + 1):
        meta = record.get(version_field(version, "meta"))
        if meta is None:
            continue
        out.append({"version": version, "created_at": record[version_field(version, "created_at")],
                    "size_bytes": int(record[version_field(version, "size")]), "meta": json.loads(meta),
                    "session_id": record.get(version_field(version, "session_id")) or None})
    return out


def parse_map(record: dict[str, str]) -> dict[str, Any]:
    """The API form of a map record (MapSummary)."""
    latest = int(record["latest"])
    return {"id": record["id"], "name": record["name"], "status": record["status"],
            "created_at": record["created_at"], "updated_at": record["updated_at"], "latest_version": latest,
            "size_bytes": int(record[version_field(latest, "size")]),
            "meta": json.loads(record[version_field(latest, "meta")])}
