"""Shared route helpers: the registry from the app, and session look-up with ownership checks."""

from __future__ import annotations

from fastapi import HTTPException, Request

from service.auth import Principal
from service.registry import Registry


def registry(request: Request) -> Registry:
    return request.app.state.registry


async def session_for(registry: Registry, principal: Principal, session_id: str, write: bool) -> dict[str, str]:
    """The raw session record, or 404; 403 when the caller may not touch it.

    Writes (streaming, delete) need the session's creator (or admin); reads need the creator, or a read/admin key.
    """
    record = await registry.get_raw(session_id)
    if record is None:
        raise HTTPException(404, f"session {session_id} not found")
    if principal.owns(record.get("owner")):
        return record
    if not write and principal.can_read_any():
        return record
    raise HTTPException(403, "this API key did not create this session")
