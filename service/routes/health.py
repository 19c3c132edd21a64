"""``GET /healthz`` (alive), ``GET /readyz`` (an index is loaded and answers: not while the
loaded version is one its background check found corrupt) and ``GET /metrics``
(Prometheus); none of them needs a key.

``/healthz`` stays ``ok`` for a corrupt version: the process is sound, and a restart would
not mend the file (it would refuse the version at start-up instead)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse, PlainTextResponse, Response

from service.deps import EngineDep, MetricsDep
from service.errors import error_body, index_corrupt
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
    responses={
        503: {
            "model": ErrorBody,
            "description": "no index loaded yet (`not_ready`), or the loaded version is "
            "corrupt (`index_corrupt`)",
        }
    },
)
def readyz(engine: EngineDep) -> Response:
    if not engine.ready:
        return JSONResponse(error_body("not_ready", "no index loaded"), 503)
    loaded = engine.current
    if loaded.verification == "corrupt":
        return index_corrupt(loaded.version).response()
    return JSONResponse({"status": "ready", "index_version": loaded.version})


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
        # the version answering may change without a reload: a failed background check
        # hands back to the previous one (service.engine)
        metrics.set_index(engine.current.version)
        metrics.set_verification(engine.current.verification)
    return metrics.response()
