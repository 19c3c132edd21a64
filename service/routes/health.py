"""``GET /healthz`` (alive), ``GET /readyz`` (an index is loaded) and ``GET /metrics``
(Prometheus); none of them needs a key."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse, PlainTextResponse, Response

from service.deps import EngineDep, MetricsDep
from service.errors import error_body
from service.reloader import update_behind
from service.schemas import ErrorBody, Health, Ready

__all__ = ["router"]

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=Ready,
    responses={503: {"model": ErrorBody, "description": "no index loaded yet"}},
)
def readyz(engine: EngineDep) -> Response:
    if not engine.ready:
        return JSONResponse(error_body("not_ready", "no index loaded"), 503)
    return JSONResponse({"status": "ready", "index_version": engine.current.version})


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    responses={
        200: {
            "description": "Prometheus text exposition format",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        }
    },
)
def prometheus(engine: EngineDep, metrics: MetricsDep) -> Response:
    metrics.set_queue(engine.queued, engine.running)
    if engine.ready:
        update_behind(engine, metrics)
    return metrics.response()
