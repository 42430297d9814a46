"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse

from protocol import keys
from service.auth import Principal, caller
from service.schemas import Health, Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
async def healthz() -> dict:
    """The gateway process is up."""
    return {"status": "ok"}


@router.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness}})
async def readyz(request: Request) -> Response:
    """Ready when Redis answers and at least one worker has a live heartbeat."""
    reg = request.app.state.registry
    try:
        await reg.client.ping()
        workers = len(await reg.live_workers())
        redis_ok = True
    except Exception:
        redis_ok, workers = False, 0
    ready = redis_ok and workers >= 1
    body = {"status": "ready" if ready else "not_ready", "redis": redis_ok, "workers": workers}
    return JSONResponse(body, status_code=200 if ready else 503)


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}})
async def metrics(request: Request, principal: Principal = Depends(caller)) -> Response:
    """Ingest counters, ack latency, queue depth, per-stage worker latency, sessions by status (read scope)."""
    request.app.state.auth.require(principal, "read")
    reg = request.app.state.registry
    workers = await reg.live_workers()
    stats = await reg.worker_stats()
    by_status = await _sessions_by_status(reg)
    body = request.app.state.metrics.render(stats, len(workers), by_status)
    return Response(body, media_type="text/plain; version=0.0.4")


async def _sessions_by_status(reg, limit: int = 10_000) -> dict[str, int]:
    members = await reg.client.zrevrangebylex(keys.SESSIONS_INDEX, "+", "-", start=0, num=limit)
    pipe = reg.client.pipeline(transaction=False)
    for member in members:
        pipe.hget(keys.session(member.decode().split(":", 1)[1]), "status")
    counts = dict.fromkeys(keys.STATUSES, 0)
    for status in await pipe.execute() if members else []:
        if status:
            counts[status.decode()] = counts.get(status.decode(), 0) + 1
    return counts
