"""Session CRUD and the fleet listing: /v1/sessions."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError

from service.auth import Principal, caller
from service.deps import check_access, map_store, registry, session_for
from service.maps import MapStore
from service.registry import Registry, parse_session
from service.schemas import ErrorBody, Session, SessionCreate, SessionList, SessionStatus

router = APIRouter(prefix="/v1/sessions", tags=["sessions"],
                   responses={401: {"model": ErrorBody}, 403: {"model": ErrorBody}})


@router.post("", status_code=201, response_model=Session,
             responses={400: {"model": ErrorBody, "description": "the body could not be parsed (not UTF-8 text)"},
                        413: {"model": ErrorBody, "description": "the body exceeds the gateway's size limit "
                              "(FLASHMONO_MAX_BODY_BYTES)"},
                        422: {"description": "invalid body: not JSON, or a field the schema or its rules refuse"},
                        429: {"model": ErrorBody, "description": "the key's quota of live sessions is used up"}})
async def create_session(body: SessionCreate, request: Request, principal: Principal = Depends(caller),
                         reg: Registry = Depends(registry), maps: MapStore = Depends(map_store)) -> dict:
    """Create a session; a worker picks it up. Needs the `stream` scope. With `map_id`, the session runs in that
    saved map (`map_mode`), at its latest version."""
    request.app.state.auth.require(principal, "stream")
    if body.preset is not None:
        check = request.app.state.validate_preset
        try:
            check(body.preset)
        except (ValueError, KeyError) as err:
            raise _invalid("preset", body.preset, f"unknown preset {body.preset!r}: {err}") from err
    in_map = await _map_fields(body, principal, maps)
    quota = request.app.state.settings.max_live_sessions
    if quota and await reg.live_sessions_of(principal.key_id) >= quota:
        raise HTTPException(429, f"this API key has {quota} live sessions, its limit (FLASHMONO_MAX_LIVE_SESSIONS): "
                                 "finish or delete one first")
    session = await reg.create_session({**body.model_dump(mode="json", exclude_none=True), **in_map},
                                       owner=principal.key_id)
    if in_map:
        await maps.add_session(in_map["map_id"], session["id"], in_map["map_mode"])
    request.app.state.metrics.sessions_created.inc()
    return session


def _invalid(field: str, value: object, message: str) -> RequestValidationError:
    """The same 422 body as every other invalid field."""
    return RequestValidationError([{"type": "value_error", "loc": ("body", field), "input": value, "msg": message}])


async def _map_fields(body: SessionCreate, principal: Principal, maps: MapStore) -> dict:
    """{map_id, map_version, map_mode} of a session created in a map (none without `map_id`): 422 for an unknown
    map, 403 for one the key may not read (`extend`: may not change)."""
    if body.map_id is None:
        return {}
    record = await maps.get_raw(body.map_id)
    if record is None:
        raise _invalid("map_id", body.map_id, f"unknown map {body.map_id!r}")
    mode = body.map_mode or "localize"
    check_access(principal, record, write=mode == "extend", what="map")
    return {"map_id": body.map_id, "map_version": int(record["latest"]), "map_mode": mode}


@router.get("", response_model=SessionList)
async def list_sessions(
    request: Request,
    status: Annotated[SessionStatus | None, Query(description="only sessions with this status")] = None,
    device_id: Annotated[str | None, Query(max_length=200)] = None,
    name: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    cursor: Annotated[str | None, Query(max_length=200, description="next_cursor of the previous page")] = None,
    principal: Principal = Depends(caller),
    reg: Registry = Depends(registry),
) -> dict:
    """Fleet listing, newest first. Keys with only the `stream` scope see the sessions they created."""
    request.app.state.auth.require(principal, "read", "stream")
    owner = None if principal.can_read_any() else principal.key_id
    sessions, next_cursor = await reg.list_sessions(status=status, device_id=device_id, name=name, limit=limit,
                                                    cursor=cursor, owner=owner)
    return {"sessions": sessions, "next_cursor": next_cursor}


@router.get("/{session_id}", response_model=Session, responses={404: {"model": ErrorBody}})
async def get_session(session_id: str, request: Request, principal: Principal = Depends(caller),
                      reg: Registry = Depends(registry)) -> dict:
    request.app.state.auth.require(principal, "read", "stream")
    return parse_session(await session_for(reg, principal, session_id, write=False))


@router.delete("/{session_id}", status_code=204, responses={404: {"model": ErrorBody}})
async def delete_session(session_id: str, request: Request, principal: Principal = Depends(caller),
                         reg: Registry = Depends(registry)) -> Response:
    """Delete the session and everything stored for it; its worker stops."""
    request.app.state.auth.require(principal, "stream")
    record = await session_for(reg, principal, session_id, write=True)
    await reg.delete_session(session_id, record)
    return Response(status_code=204)
