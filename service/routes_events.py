"""WS /v1/sessions/{id}/events: a read-only feed of what a session's stream reports (pose, loop_closed,
tracking_lost, relocalized, initialized, error, finished), for viewers that do not send the frames.

It relays the session's outbox from the moment of connection (the trajectory endpoint has the history) through the
gateway's one OutboxHub, and closes after "finished" (1000) or when the session is deleted (4404). Nothing the
client sends is read but its close.
"""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, HTTPException, WebSocket, WebSocketDisconnect

from protocol import keys
from protocol.messages import ErrorMessage
from service.auth import request_key
from service.deps import session_for
from service.hardening import origin_allowed
from service.outbox_hub import SESSION_DELETED, OutboxHub
from service.registry import Registry
from worker.runtime.outage import REDIS_DOWN

router = APIRouter()
_AUTH_CODES = {401: "unauthorized", 403: "forbidden", 404: "not_found"}


@router.websocket("/v1/sessions/{session_id}/events")
async def session_events(websocket: WebSocket, session_id: str) -> None:
    app = websocket.app
    reg: Registry = app.state.registry
    origin = websocket.headers.get("origin")
    if not origin_allowed(origin, websocket.headers.get("host"), app.state.settings.allowed_origins):
        await _refuse(websocket, "forbidden_origin", f"Origin {origin} may not connect here", 4403)
        return
    try:
        principal = app.state.auth.principal(request_key(websocket, allow_query=True))
        app.state.auth.require(principal, "read", "stream")
        record = await session_for(reg, principal, session_id, write=False)
        newest = await reg.client.xrevrange(keys.outbox(session_id), count=1)
    except REDIS_DOWN as err:
        await _refuse(websocket, "unavailable", f"the session store (Redis) is unreachable: {err}", 1013)
        return
    except HTTPException as err:
        await _refuse(websocket, _AUTH_CODES.get(err.status_code, "error"), str(err.detail), 4000 + err.status_code)
        return
    await websocket.accept()
    if record["status"] in ("finished", "failed"):
        await websocket.send_text(json.dumps({"type": record["status"], "frames": int(record.get("frames_processed")
                                                                                       or 0)}))
        await websocket.close(1000)
        return
    hub: OutboxHub = app.state.outbox_hub
    subscription = hub.subscribe(session_id, newest[0][0].decode() if newest else "0-0")
    closed = asyncio.create_task(_until_closed(websocket))
    try:
        while True:
            next_text = asyncio.create_task(subscription.queue.get())
            done, _ = await asyncio.wait({next_text, closed}, return_when=asyncio.FIRST_COMPLETED)
            if closed in done:
                next_text.cancel()
                return
            text = next_text.result()
            if text is SESSION_DELETED:
                await websocket.send_text(ErrorMessage(code="not_found", message="the session was deleted").to_json())
                await websocket.close(4404)
                return
            await websocket.send_text(text)
            if text.startswith('{"type": "finished"'):
                await websocket.close(1000)
                return
    except (WebSocketDisconnect, RuntimeError):
        return  # the viewer went away mid-send
    finally:
        hub.unsubscribe(subscription)
        closed.cancel()


async def _until_closed(websocket: WebSocket) -> None:
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
    except (WebSocketDisconnect, RuntimeError):
        return


async def _refuse(websocket: WebSocket, code: str, message: str, close_code: int) -> None:
    await websocket.accept()
    await websocket.send_text(ErrorMessage(code=code, message=message).to_json())
    await websocket.close(close_code)
