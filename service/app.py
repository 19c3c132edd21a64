"""The FastAPI application: the engine, auth, limits and metrics around the routers.

``create_app(settings)`` builds an app whose lifespan opens the index (once) and closes it;
``hmpf-serve`` runs it under uvicorn. Routes (OpenAPI at ``/docs``), one router per concern:

* :mod:`service.routes.localize`: ``POST /v1/localize``: one image (multipart field ``image``
  or the raw body with an image content type); optional ``lat``, ``lon``, ``radius_m``,
  ``top_k``, ``vehicle_id`` (sequence mode, with ``track`` and ``timestamp``:
  :mod:`service.vehicle`) as query parameters or form fields. ``POST /v1/localize/batch``:
  multipart, one or more ``images`` fields; one answer each, in order (a bad image gets its
  own error entry, the others are answered).
* :mod:`service.routes.index`: ``GET /v1/index``; ``POST /v1/index/reload`` (admin); with
  ``watch_current_s`` a change of the index's ``CURRENT`` reloads too (:mod:`service.reloader`).
* :mod:`service.routes.inspect`: ``GET /inspect`` (the inspection page, its files under
  ``/inspect/static``), ``GET /v1/references``, ``GET /v1/references/{reference}/thumbnail``,
  ``POST /v1/evidence``.
* :mod:`service.routes.health`: ``GET /healthz``, ``GET /readyz``, ``GET /metrics`` (no key
  needed).

The routes take the engine, the settings, the metrics and the caller's key as ``Annotated``
dependencies (:mod:`service.deps`); errors are answered by :mod:`service.errors`.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from hmpf.cli.common import package_version
from service.auth import KeyStore
from service.engine import Engine
from service.errors import install_handlers
from service.limits import ActiveLimit, BodyDeadline, BodyLimit, HeadLimit
from service.metrics import Metrics
from service.openapi import document_limits
from service.recording import Recorder
from service.reloader import CurrentWatch, update_behind
from service.routes import health, index, inspect, localize
from service.routes.docs import install_docs
from service.settings import Settings
from service.vehicle import Tracker

__all__ = ["create_app"]

log = logging.getLogger("hmpf.service")
#: Multipart fields other than files that a request may have (its optional fields and a few
#: spare), as FastAPI's form parser limit.
_MAX_FORM_FIELDS = 16


def create_app(settings: Settings, engine: Engine | None = None) -> FastAPI:
    """The service app. ``engine`` (tests) replaces the one built from ``settings``."""
    keys = KeyStore.load(settings.keys_file) if settings.auth and settings.keys_file else None
    engine = engine or Engine(
        settings.index,
        workers=settings.worker_count,
        queue=settings.queue,
        threads_per_worker=settings.thread_count,
        accept_threshold=settings.accept_threshold,
        approx_k=settings.approx_k,
        faiss_params=settings.faiss_params,
    )
    metrics = Metrics()
    # versions the background check finds corrupt (service.engine), counted
    engine.on_corrupt = lambda loaded: metrics.index_corrupt.inc()
    app = FastAPI(
        title="hmpf",
        summary="Visual place recognition: which stored reference image does this frame show?",
        version=package_version(),
        lifespan=_lifespan,
        docs_url=None,  # served from the package, not a CDN (service.routes.docs)
        redoc_url=None,
    )
    app.state.engine = engine
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.tracker = Tracker(settings, metrics)
    app.state.keys = keys
    install_handlers(app)
    app.add_middleware(BodyLimit, limit_for=_body_limits(settings))
    app.add_middleware(BodyDeadline, timeout_s=settings.body_timeout_s)
    app.add_middleware(
        ActiveLimit, limit=settings.max_connections, retry_after_s=settings.retry_after_s
    )
    app.add_middleware(HeadLimit, limit=settings.max_header_bytes)
    app.middleware("http")(metrics.middleware)
    app.include_router(
        localize.router,
        form_limits={"max_files": settings.max_batch, "max_fields": _MAX_FORM_FIELDS},
    )
    app.include_router(index.router)
    app.include_router(inspect.router, form_limits={"max_files": 1, "max_fields": _MAX_FORM_FIELDS})
    app.mount("/inspect/static", StaticFiles(directory=inspect.STATIC), name="inspect-static")
    app.include_router(health.router)
    install_docs(app)
    document_limits(app, settings)
    return app


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Open the index (unless the engine is loaded already) and close it at shutdown; with
    recording on, start the experience recorder and, at shutdown, write what it holds."""
    settings: Settings = app.state.settings
    engine: Engine = app.state.engine
    if not settings.auth:
        log.warning("authentication is OFF (auth=false): every client may query and reload")
    _limit_threads(settings.thread_count)
    if not engine.ready:
        engine.load()
    app.state.metrics.set_index(engine.current.version)
    update_behind(engine, app.state.metrics)
    watch = None
    if settings.watch_current_s > 0:
        watch = CurrentWatch(engine, app.state.metrics, settings.watch_current_s)
        watch.start()
        log.info("watching %s/CURRENT every %g s", engine.root, settings.watch_current_s)
    recorder = Recorder.for_settings(settings, app.state.metrics)
    app.state.recorder = recorder
    if recorder is not None:
        recorder.start()
    try:
        yield
    finally:
        if watch is not None:
            await watch.stop()
        if recorder is not None:
            recorder.stop()
        engine.close()


def _limit_threads(n: int) -> None:
    """Cap BLAS/OpenMP pools (threadpoolctl) and, when torch is loaded, its pool for the
    workers."""
    try:
        from threadpoolctl import threadpool_limits  # optional: absent, the pools keep their sizes

        threadpool_limits(n)
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency of the extra
        pass
    # torch is not imported for this: the CNN methods run the index's ONNX models without it
    # (a serving install has no torch), and where a query does run torch (an index without
    # stored models, HMPF_CNN_RUNTIME=torch) the forward pass sets its threads itself.
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
    # FAISS's OpenMP pool, which is loaded later (with the index) and so escapes the limit
    # above; left at the core count, one single-query search spin-waits on busy cores (an
    # approximate tier 1 took 10x longer on a loaded two-core machine).
    try:
        import faiss  # here, not at the top: only to cap its pool (the reader imports it)
    except ImportError:  # pragma: no cover - the index extra is part of a serving install
        return
    faiss.omp_set_num_threads(n)


def _body_limits(settings: Settings) -> Callable[[str], int]:
    overhead = 64 * 1024  # multipart headers and form fields
    single = settings.max_upload_bytes + overhead
    batch = settings.max_upload_bytes * settings.max_batch + overhead

    def limit(path: str) -> int:
        if path.rstrip("/") in ("/v1/localize", "/v1/evidence"):
            return single
        if path.rstrip("/") == "/v1/localize/batch":
            return batch
        return overhead

    return limit
