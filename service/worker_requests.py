"""Asking a worker for what a session's engine makes (renders, map files, map packages): the owning worker while
the session is live, any worker once it is finished (restored from its snapshot)."""

from __future__ import annotations

import time
from typing import Any

from fastapi import HTTPException, Request

from protocol import keys
from service.registry import Registry, RequestTimeout
from service.schemas import ErrorBody

# Seconds a client waits before asking again when no worker owns a live session (a worker takes it over within a
# lease: a few seconds)
NO_OWNER_RETRY_AFTER_S = 2
WORKER_ANSWERS: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorBody, "description": "the session failed, or has no map yet (no frame streamed)"},
    503: {"model": ErrorBody, "description": "no worker owns this live session right now (its worker went away and "
          "another takes it over, or the fleet is full): retry after `Retry-After` seconds",
          "headers": {"Retry-After": {"description": "seconds to wait before retrying",
                                      "schema": {"type": "integer"}}}},
    504: {"model": ErrorBody, "description": "the owning worker did not answer within the request timeout"},
}


async def ask_worker(request: Request, reg: Registry, session_id: str, record: dict[str, str], kind: str,
                     params: dict[str, Any]) -> tuple[str, bytes]:
    """(content type, body) of the worker's answer to request `kind` on the session (its raw `record`); the worker's
    refusals, a failed or frameless session (409), no owner (503) and no answer (504) as HTTPExceptions."""
    status = record["status"]
    live = status in keys.LIVE_STATUSES
    if status == "failed":
        raise HTTPException(409, f"session failed: {record.get('error', '')}")
    if status == "created":  # no worker takes a session before its first frame: there is nothing to ask it
        raise HTTPException(409, "the session has no map yet: no frame has been streamed to it")
    if live and await reg.lease_holder(session_id) is None:
        raise HTTPException(503, "no worker owns this session right now; retry shortly",
                            headers={"Retry-After": str(NO_OWNER_RETRY_AFTER_S)})
    t0 = time.perf_counter()
    try:
        reply = await reg.request(session_id, kind, params, live=live,
                                  timeout_s=request.app.state.settings.request_timeout_s)
    except RequestTimeout as err:
        raise HTTPException(504, str(err)) from err
    request.app.state.metrics.request_latency.labels(kind).observe(time.perf_counter() - t0)
    if not reply.get("ok"):
        raise HTTPException(int(reply.get("status", 500)), reply.get("detail", "worker error"))
    return reply["content_type"], reply["body"]
