"""Prometheus metrics of one app (its own registry, so several apps can coexist in tests).

* ``hmpf_requests_total{route,method,status}``
* ``hmpf_request_seconds{route}``: end-to-end latency histogram per route
* ``hmpf_stage_seconds{stage}``: queue, decode, extract, hierarchy, total per query
* ``hmpf_queue_depth``, ``hmpf_running``: admitted queries waiting / computing
* ``hmpf_index_info{version}``: 1 for the loaded index version
"""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)
from starlette.requests import Request
from starlette.responses import Response

__all__ = ["Metrics"]

_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0, 5.0, 10.0)
_STAGES = ("queue", "decode", "extract", "hierarchy", "total")
#: HTTP methods kept as label values; any other is counted as "other" (a client must not be
#: able to create label values, and so time series, at will).
_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "hmpf_requests", "HTTP requests", ["route", "method", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "hmpf_request_seconds",
            "request latency",
            ["route"],
            buckets=_BUCKETS,
            registry=self.registry,
        )
        self.stages = Histogram(
            "hmpf_stage_seconds",
            "time per query stage",
            ["stage"],
            buckets=_BUCKETS,
            registry=self.registry,
        )
        self.queue = Gauge("hmpf_queue_depth", "admitted queries waiting", registry=self.registry)
        self.running = Gauge("hmpf_running", "queries computing", registry=self.registry)
        self.index = Gauge(
            "hmpf_index_info", "loaded index version", ["version"], registry=self.registry
        )
        self._version: str | None = None

    async def middleware(
        self, request: Request, call_next: Callable[[Request], Awaitable[Response]]
    ) -> Response:
        start = time.perf_counter()
        status = 500
        try:
            response = await call_next(request)
            status = response.status_code
            return response
        finally:
            route = request.scope.get("route")
            name = getattr(route, "path", None) or "unmatched"
            method = request.method if request.method in _METHODS else "other"
            self.requests.labels(name, method, str(status)).inc()
            self.latency.labels(name).observe(time.perf_counter() - start)

    def observe_stages(self, timing_ms: Mapping[str, Any]) -> None:
        for stage in _STAGES:
            v = timing_ms.get(stage)
            if isinstance(v, int | float):
                self.stages.labels(stage).observe(v / 1e3)

    def set_queue(self, queued: int, running: int) -> None:
        self.queue.set(queued)
        self.running.set(running)

    def set_index(self, version: str) -> None:
        if self._version is not None:
            self.index.remove(self._version)
        self.index.labels(version).set(1)
        self._version = version

    def response(self) -> Response:
        return Response(generate_latest(self.registry), media_type=CONTENT_TYPE_LATEST)
