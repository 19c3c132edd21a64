"""The FastAPI application: routes, auth, limits and metrics around :class:`Engine`.

``create_app(settings)`` builds an app whose lifespan opens the index (once) and closes it;
``hmpf-serve`` runs it under uvicorn. Routes (OpenAPI at ``/docs``):

* ``POST /v1/localize``: one image (multipart field ``image`` or the raw body with an image
  content type); optional ``lat``, ``lon``, ``radius_m``, ``top_k``, ``vehicle_id`` as query
  parameters or form fields.
* ``POST /v1/localize/batch``: multipart, one or more ``images`` fields; one answer each,
  in order (a bad image gets its own error entry, the others are answered).
* ``GET /v1/index``; ``POST /v1/index/reload`` (admin).
* ``GET /healthz``, ``GET /readyz``, ``GET /metrics`` (no key needed).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor
from contextlib import asynccontextmanager
from typing import Any

import numpy as np
from fastapi import Depends, FastAPI, Request
from fastapi.responses import JSONResponse, Response
from pydantic import ValidationError
from starlette.datastructures import FormData, UploadFile

from hmpf.errors import HmpfError
from hmpf.hierarchy import HierarchyResult
from hmpf.index import layout as L
from service.auth import ApiKey, KeyStore
from service.engine import Engine, Loaded, Prior, confidence, run_query
from service.errors import ApiError, error_body, install_handlers
from service.images import check_content_type, decode_upload
from service.limits import BodyLimit, BodyTooLarge
from service.metrics import Metrics
from service.schemas import (
    BatchResponse,
    ErrorBody,
    IndexInfo,
    LocalizeParams,
    LocalizeResponse,
)
from service.settings import Settings

__all__ = ["create_app"]

log = logging.getLogger("hmpf.service")

_ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorBody} for code in (401, 403, 413, 415, 422, 503)
}
_LOCALIZE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["image"],
                    "properties": {
                        "image": {"type": "string", "format": "binary"},
                        "lat": {"type": "number"},
                        "lon": {"type": "number"},
                        "radius_m": {"type": "number"},
                        "top_k": {"type": "integer"},
                        "vehicle_id": {"type": "string"},
                    },
                }
            },
            "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
            "image/png": {"schema": {"type": "string", "format": "binary"}},
            "image/webp": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}
_BATCH_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["images"],
                    "properties": {
                        "images": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                        },
                        "top_k": {"type": "integer"},
                        "vehicle_id": {"type": "string"},
                    },
                }
            }
        },
    }
}
_PARAM_FIELDS = set(LocalizeParams.model_fields)


def create_app(settings: Settings, engine: Engine | None = None) -> FastAPI:
    """The service app. ``engine`` (tests) replaces the one built from ``settings``."""
    keys = KeyStore.load(settings.keys_file) if settings.auth and settings.keys_file else None
    eng = engine or Engine(
        settings.index,
        workers=settings.worker_count,
        queue=settings.queue,
        threads_per_worker=settings.thread_count,
        accept_threshold=settings.accept_threshold,
    )
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if not settings.auth:
            log.warning("authentication is OFF (auth=false): every client may query and reload")
        _limit_threads(settings.thread_count)
        if not eng.ready:
            eng.load()
        metrics.set_index(eng.current.version)
        yield
        eng.close()

    app = FastAPI(
        title="hmpf",
        summary="Visual place recognition: which stored reference image does this frame show?",
        version=_version(),
        lifespan=lifespan,
    )
    app.state.engine = eng
    app.state.settings = settings
    app.state.metrics = metrics
    install_handlers(app)
    app.add_exception_handler(BodyTooLarge, _too_large)  # type: ignore[arg-type]
    app.add_middleware(BodyLimit, limit_for=_body_limits(settings))
    app.middleware("http")(metrics.middleware)

    def role(required: str) -> Callable[[Request], ApiKey | None]:
        def check(request: Request) -> ApiKey | None:
            if keys is None:
                return None
            key = keys.check(request.headers.get("x-api-key"))
            if key is None:
                raise ApiError(
                    401,
                    "unauthorized",
                    "missing or invalid API key (header X-API-Key)",
                    {"WWW-Authenticate": "ApiKey"},
                )
            if not key.allows(required):
                raise ApiError(403, "forbidden", f"this key's role may not {required}-only routes")
            return key

        return check

    vehicle = Depends(role("vehicle"))
    admin = Depends(role("admin"))

    # -- localisation -------------------------------------------------------------------------
    @app.post(
        "/v1/localize",
        response_model=LocalizeResponse,
        responses=_ERRORS,
        openapi_extra=_LOCALIZE_BODY,
        tags=["localize"],
    )
    async def localize(request: Request, key: ApiKey | None = vehicle) -> dict[str, Any]:
        """Localise one image against the current index version."""
        ctype = request.headers.get("content-type", "")
        if ctype.startswith("multipart/form-data"):
            form = await _form(request, max_files=1)
            try:
                upload = _single_file(form, "image")
                params = _params(request, form)
                _check_size(upload, settings.max_upload_bytes, "image")
                data = await upload.read()
                file_type = upload.content_type
            finally:
                await form.close()
        else:
            check_content_type(ctype or None)
            if not ctype:
                raise ApiError(
                    415,
                    "unsupported_media_type",
                    "send the image as multipart field 'image' or as the body with "
                    "Content-Type image/jpeg, image/png or image/webp",
                )
            params = _params(request, None)
            data = await request.body()
            file_type = ctype
        _check_top_k(params, settings)
        if len(data) > settings.max_upload_bytes:
            raise _upload_too_large(settings.max_upload_bytes)
        if not eng.admit(1):
            raise _busy(settings)
        ((ok, value),) = await eng.run([_job(data, file_type, params, "image")])
        if not ok:
            raise value
        metrics.observe_stages(value["timing_ms"])
        return value

    @app.post(
        "/v1/localize/batch",
        response_model=BatchResponse,
        responses=_ERRORS,
        openapi_extra=_BATCH_BODY,
        tags=["localize"],
    )
    async def localize_batch(request: Request, key: ApiKey | None = vehicle) -> dict[str, Any]:
        """Localise several images (multipart, ``images`` fields); answers in order."""
        if not request.headers.get("content-type", "").startswith("multipart/form-data"):
            raise ApiError(
                415, "unsupported_media_type", "send the images as multipart fields 'images'"
            )
        form = await _form(request, max_files=settings.max_batch)
        try:
            files = form.getlist("images")
            if not files or not all(isinstance(f, UploadFile) for f in files):
                raise ApiError(422, "invalid_request", "images: at least one file is required")
            extra = [
                k for k, v in form.multi_items() if isinstance(v, UploadFile) and k != "images"
            ]
            if extra:
                raise ApiError(422, "invalid_request", f"unexpected file field {extra[0]!r}")
            params = _params(request, form, exclude=("images",))  # one prior for all images
            for i, f in enumerate(files):
                _check_size(f, settings.max_upload_bytes, f"images[{i}]")  # type: ignore[arg-type]
            blobs = [(await f.read(), f.content_type) for f in files]  # type: ignore[union-attr]
        finally:
            await form.close()
        _check_top_k(params, settings)
        for i, (data, _) in enumerate(blobs):
            if len(data) > settings.max_upload_bytes:
                raise _upload_too_large(settings.max_upload_bytes, f"images[{i}]")
        # A batch runs its images in up to `workers` lanes, one slot each, so that any batch
        # size fits the admission limit and a batch cannot take the queue's slots.
        lanes = min(len(blobs), eng.workers)
        if not eng.admit(lanes):
            raise _busy(settings)
        jobs = [_job(d, c, params, f"images[{i}]") for i, (d, c) in enumerate(blobs)]
        version = eng.current.version
        results: list[dict[str, Any]] = []
        for i, (ok, value) in enumerate(await eng.run(jobs, lanes)):
            if ok:
                metrics.observe_stages(value["timing_ms"])
                version = value["index_version"]
                results.append({"index": i, "result": value})
            elif isinstance(value, ApiError):
                results.append(
                    {"index": i, "error": {"code": value.code, "message": value.message}}
                )
            else:
                log.error("batch item %d failed", i, exc_info=value)
                results.append(
                    {"index": i, "error": {"code": "internal", "message": "internal error"}}
                )
        return {"results": results, "index_version": version}

    def _job(
        data: bytes, ctype: str | None, params: LocalizeParams, source: str
    ) -> Callable[[Loaded], dict[str, Any]]:
        """One image's work on a query thread, with the request's lease on a version."""
        t_start = time.perf_counter()

        def work(loaded: Loaded) -> dict[str, Any]:
            timing: dict[str, Any] = {"queue": (time.perf_counter() - t_start) * 1e3}
            t = time.perf_counter()
            image = decode_upload(
                data, max_pixels=settings.max_pixels, content_type=ctype, source=source
            )
            timing["decode"] = (time.perf_counter() - t) * 1e3
            try:
                body = _localize(loaded, image, params, timing, eng.compute)
            except HmpfError as exc:
                raise ApiError(422, "invalid_image", f"{source}: {exc}") from None
            timing["total"] = (time.perf_counter() - t_start) * 1e3
            return body

        return work

    # -- index --------------------------------------------------------------------------------
    @app.get("/v1/index", response_model=IndexInfo, responses=_ERRORS, tags=["index"])
    def index_info(key: ApiKey | None = vehicle) -> dict[str, Any]:
        """The loaded index version: counts, methods, config, build time."""
        loaded = eng.current
        r = loaded.reader
        m = r.manifest
        return {
            "root": str(eng.root),
            "version": r.version,
            "versions": L.list_versions(eng.root),
            "references": r.n,
            "methods": {
                mid: {
                    k: v
                    for k, v in info.items()
                    if k in ("type", "kind", "version", "dim", "faiss", "params")
                }
                for mid, info in m.get("methods", {}).items()
            },
            "config": m.get("config", {}).get("resolved", {}),
            "built": {
                "created": m.get("created"),
                "operation": m.get("operation"),
                "seconds": m.get("summary", {}).get("seconds"),
                "images_per_s": m.get("summary", {}).get("images_per_s"),
                "packages": m.get("packages", {}),
            },
            "has_positions": loaded.has_positions,
            "threshold": loaded.threshold,
            "loaded_at": loaded.loaded_at,
        }

    @app.post("/v1/index/reload", responses=_ERRORS, tags=["index"])
    async def reload(key: ApiKey | None = admin) -> dict[str, Any]:
        """Switch to the index's current version; running queries finish on the old one."""
        try:
            old, new = await eng.reload()
        except HmpfError as exc:
            raise ApiError(
                409, "index_unusable", f"kept version {eng.current.version}: {exc}"
            ) from None
        except Exception:
            log.exception("reload of %s failed", eng.root)
            raise ApiError(
                409,
                "index_unusable",
                f"kept version {eng.current.version}: the current version could not be "
                "loaded (see the service log)",
            ) from None
        metrics.set_index(new)
        return {"previous": old, "version": new, "changed": old != new}

    # -- health and metrics -------------------------------------------------------------------
    @app.get("/healthz", tags=["health"])
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", tags=["health"], responses={503: {"model": ErrorBody}})
    def readyz() -> Response:
        if not eng.ready:
            return JSONResponse(error_body("not_ready", "no index loaded"), 503)
        return JSONResponse({"status": "ready", "index_version": eng.current.version})

    @app.get("/metrics", tags=["health"])
    def prometheus() -> Response:
        metrics.set_queue(eng.queued, eng.running)
        return metrics.response()

    return app


# -- helpers ------------------------------------------------------------------------------------
def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hmpf")
    except PackageNotFoundError:
        return "0"


def _limit_threads(n: int) -> None:
    """Cap BLAS/OpenMP pools (threadpoolctl) and torch's inter-op pool for the workers."""
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(n)
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency of the extra
        pass
    try:
        import torch

        torch.set_num_threads(n)
    except ImportError:  # pragma: no cover
        pass


def _body_limits(settings: Settings) -> Callable[[str], int]:
    overhead = 64 * 1024  # multipart headers and form fields
    single = settings.max_upload_bytes + overhead
    batch = settings.max_upload_bytes * settings.max_batch + overhead

    def limit(path: str) -> int:
        if path.rstrip("/") == "/v1/localize":
            return single
        if path.rstrip("/") == "/v1/localize/batch":
            return batch
        return overhead

    return limit


async def _too_large(request: Request, exc: BodyTooLarge) -> JSONResponse:
    return JSONResponse(
        error_body("payload_too_large", f"request body exceeds {exc.limit} bytes"), 413
    )


def _upload_too_large(limit: int, what: str = "image") -> ApiError:
    return ApiError(413, "payload_too_large", f"{what} exceeds the upload limit of {limit} bytes")


def _check_size(upload: UploadFile, limit: int, what: str) -> None:
    """Refuse an uploaded file from its parsed size, before reading it into memory."""
    if upload.size is not None and upload.size > limit:
        raise _upload_too_large(limit, what)


def _busy(settings: Settings) -> ApiError:
    return ApiError(
        503,
        "overloaded",
        "all workers are busy and the queue is full; retry later",
        {"Retry-After": str(settings.retry_after_s)},
    )


async def _form(request: Request, max_files: int) -> FormData:
    try:
        return await request.form(max_files=max_files, max_fields=16)
    except BodyTooLarge:
        raise
    except Exception as exc:  # starlette's MultiPartException and parser errors
        raise ApiError(422, "invalid_request", f"malformed multipart body: {exc}") from None


def _single_file(form: FormData, name: str) -> UploadFile:
    files = [v for k, v in form.multi_items() if isinstance(v, UploadFile)]
    named = form.getlist(name)
    if len(named) != 1 or not isinstance(named[0], UploadFile):
        raise ApiError(422, "invalid_request", f"{name}: exactly one file is required")
    if len(files) != 1:
        raise ApiError(422, "invalid_request", "one file per request; use /v1/localize/batch")
    return named[0]


def _params(
    request: Request, form: FormData | None, exclude: tuple[str, ...] = ("image",)
) -> LocalizeParams:
    raw: dict[str, Any] = {}
    for k, v in request.query_params.multi_items():
        if k in raw:
            raise ApiError(422, "invalid_request", f"{k}: given twice")
        raw[k] = v
    if form is not None:
        for k, value in form.multi_items():
            if k in exclude or isinstance(value, UploadFile):
                continue
            if k in raw:
                raise ApiError(422, "invalid_request", f"{k}: given twice")
            raw[k] = value
    unknown = sorted(set(raw) - _PARAM_FIELDS)
    if unknown:
        raise ApiError(
            422,
            "invalid_request",
            f"unknown field {unknown[0]!r}; allowed: {', '.join(sorted(_PARAM_FIELDS))}",
        )
    try:
        return LocalizeParams.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first.get("loc", ())) or "request"
        raise ApiError(422, "invalid_request", f"{loc}: {first.get('msg')}") from None


def _check_top_k(params: LocalizeParams, settings: Settings) -> None:
    if params.top_k > settings.max_top_k:
        raise ApiError(
            422, "invalid_request", f"top_k: at most {settings.max_top_k} (got {params.top_k})"
        )


def _localize(
    loaded: Loaded,
    image: np.ndarray,
    params: LocalizeParams,
    timing: dict[str, Any],
    executor: Executor,
) -> dict[str, Any]:
    prior = None
    prior_json: dict[str, Any] | None = None
    if params.lat is not None:
        assert params.lon is not None and params.radius_m is not None
        prior = Prior(params.lat, params.lon, params.radius_m)
        prior_json = {
            "lat": params.lat,
            "lon": params.lon,
            "radius_m": params.radius_m,
            "applied": loaded.has_positions,
            "reason": None if loaded.has_positions else "the index has no reference positions",
        }
    result, allowed = run_query(loaded, image, prior, timing, executor)
    if prior_json is not None and allowed is not None:
        prior_json["references"] = int(len(allowed))
    body: dict[str, Any] = {
        "index_version": loaded.version,
        "vehicle_id": params.vehicle_id,
        "threshold": loaded.threshold,
        "prior": prior_json,
    }
    if result is None:
        body.update(match=None, candidates=[], tiers=[])
        timing["hierarchy"] = 0.0
    else:
        ids = allowed if allowed is not None else None
        body.update(_result_json(loaded, result, ids, params.top_k))
        timing["tiers"] = [t.time_ms for t in result.tiers]
        timing["fusion"] = result.fusion_ms
    body["timing_ms"] = timing
    return body


def _result_json(
    loaded: Loaded, result: HierarchyResult, ids: np.ndarray | None, top_k: int
) -> dict[str, Any]:
    reader = loaded.reader
    names = reader.refs.names
    meta = reader.refs.meta

    def gid(i: int) -> int:
        return int(ids[i]) if ids is not None else int(i)

    def ref(i: int) -> dict[str, Any]:
        g = gid(i)
        return {"reference_id": g, "name": names[g]}

    def num(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    z = dict(zip(result.final_candidates.tolist(), result.combined.tolist(), strict=True))
    ranking = result.ranking()[:top_k]
    candidates = [{**ref(int(i)), "score": num(z[int(i)])} for i in ranking]
    tiers = []
    cfg_tiers = loaded.hierarchy.config.tiers
    for t, tier in enumerate(result.tiers):
        uniq = list(dict.fromkeys(int(i) for i in tier.candidates))
        tiers.append(
            {
                "tier": t + 1,
                "methods": tier.methods,
                "k": cfg_tiers[t].k,
                "inputs": int(len(np.unique(tier.inputs)))
                if tier.inputs is not None
                else len(names)
                if ids is None
                else len(ids),
                "candidates": [
                    {**ref(i), "scores": {m: num(float(tier.scores[m][i])) for m in tier.methods}}
                    for i in uniq
                ],
                "time_ms": tier.time_ms,
            }
        )
    match = None
    if result.match >= 0:
        g = gid(result.match)
        lat = float(meta["lat"][g]) if "lat" in meta else float("nan")
        lon = float(meta["lon"][g]) if "lon" in meta else float("nan")
        quality = result.quality if math.isfinite(result.quality) else float("-inf")
        match = {
            "reference_id": g,
            "name": names[g],
            "lat": num(lat),
            "lon": num(lon),
            "score": num(result.quality) or 0.0,
            "confidence": confidence(result.quality, len(result.final_candidates)),
            "accepted": bool(quality >= loaded.threshold),
        }
    return {"match": match, "candidates": candidates, "tiers": tiers}
