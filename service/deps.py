"""Shared route helpers: the registry and the map store from the app, and session and map look-ups with ownership
checks."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

from fastapi import HTTPException, Request

from service.auth import Principal
from service.maps import MapStore
from service.registry import Registry


def registry(request: Request) -> Registry:
    return request.app.state.registry


def map_store(request: Request) -> MapStore:
    return request.app.state.maps


def check_access(principal: Principal, record: dict[str, str], write: bool, what: str) -> None:
    """403 unless the caller may touch `record` (a session's or a map's): writes (streaming, delete, extending a map)
    need its creator (or admin); reads need its creator, or a read/admin key."""
    if principal.owns(record.get("owner")) or (not write and principal.can_read_any()):
        return
    raise HTTPException(403, f"this API key did not create this {what}")


async def session_for(registry: Registry, principal: Principal, session_id: str, write: bool) -> dict[str, str]:
    """The raw session record, or 404; 403 when the caller may not touch it (`check_access`)."""
    return await _record_for(registry.get_raw, principal, session_id, write, "session")


async def map_for(maps: MapStore, principal: Principal, map_id: str, write: bool) -> dict[str, str]:
    """The raw map record, or 404; 403 when the caller may not touch it (`check_access`)."""
    return await _record_for(maps.get_raw, principal, map_id, write, "map")


async def _record_for(load: Callable[[str], Awaitable[dict[str, str] | None]], principal: Principal, item_id: str,
                      write: bool, what: str) -> dict[str, str]:
    record = await load(item_id)
    if record is None:
        raise HTTPException(404, f"{what} {item_id} not found")
    check_access(principal, record, write, what)
    return record
