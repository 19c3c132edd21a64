"""Prometheus metrics of one app (its own registry, so several apps can coexist in tests).

* ``hmpf_requests_total{route,method,status}``: ``status`` is the HTTP status answered, or
  499 for a client that hung up before its request was read (nothing answered)
* ``hmpf_request_seconds{route}``: end-to-end latency histogram per route
* ``hmpf_stage_seconds{stage}``: queue, decode, extract, hierarchy, total per query
* ``hmpf_queue_depth``, ``hmpf_running``: admitted queries waiting / computing
* ``hmpf_index_info{version}``: 1 for the loaded index version
* ``hmpf_index_behind``: 1 while the index's ``CURRENT`` names another version than the loaded
  one (or cannot be read), checked at each scrape: a replica left on an old version says so
* ``hmpf_index_verification{state}``: 1 for how the loaded version's files were verified
  (:data:`~service.engine.VERIFICATION_STATES`: ``full``, hashed before it answered;
  ``checking``, opened by its verification stamp, the full check running in the background;
  ``passed``, that check found every byte sound; ``corrupt``, it did not: no answers),
  checked at each scrape
* ``hmpf_index_corrupt_total``: versions the background check found corrupt (each logged
  as an error; alert on any increase)
* ``hmpf_index_reloads_total{trigger}`` and ``hmpf_index_reload_failures_total{trigger}``:
  reloads that switched versions and reloads that failed (the loaded version stayed), by
  ``request`` (``POST /v1/index/reload``) or ``watch`` (``watch_current_s``)
* sequence mode (requests with a ``vehicle_id``): ``hmpf_sequence_frames_total{status}``
  (started, tracking, reset, out_of_order), ``hmpf_sequence_resets_total{reason}`` (expired,
  index_changed), ``hmpf_sequence_refused_total{reason}`` (track tokens answered 422:
  malformed, signature, vehicle), ``hmpf_sequence_answers_total{locked}`` (whether the answer
  was locked: accepted) and ``hmpf_sequence_update_seconds`` (the filter's time)
* experience recording (setting ``experience_log``, :mod:`service.recording`):
  ``hmpf_experience_recorded_total`` (frames appended to the log),
  ``hmpf_experience_dropped_total{reason}`` (``queue_full``: the recorder's queue was full;
  ``error``: the log could not be opened or written, e.g. a full disk; ``bound``: recorded
  frames deleted with the oldest segments to keep the log within its size),
  ``hmpf_experience_queue`` (frames waiting for the disk), ``hmpf_experience_bytes`` (the
  log's size on disk) and ``hmpf_experience_lead_bytes`` (the lead-in frames held in memory,
  setting ``experience_lead_frames``)

Every label value comes from a fixed set in the code, never from a request.
"""

from __future__ import annotations

import contextlib
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

from service.engine import VERIFICATION_STATES
from service.track import REFUSALS, RESET_REASONS, STATUSES

__all__ = ["DROP_REASONS", "RELOAD_TRIGGERS", "Metrics"]

#: What started a reload: ``POST /v1/index/reload`` or the watch on ``CURRENT``.
RELOAD_TRIGGERS = ("request", "watch")

#: Why a frame meant for the experience log is not (or no longer) in it.
DROP_REASONS = ("queue_full", "error", "bound")

_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0, 5.0, 10.0)
_STAGES = ("queue", "decode", "extract", "hierarchy", "total")
_FILTER_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.1)
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
        self.index_behind = Gauge(
            "hmpf_index_behind",
            "1 while the index's CURRENT names another version than the loaded one",
            registry=self.registry,
        )
        self.index_verification = Gauge(
            "hmpf_index_verification",
            "1 for how the loaded index version's files were verified: full (hashed before "
            "it answered), checking (opened by its verification stamp, full check running "
            "in the background), passed (that check found them sound), corrupt (it did not)",
            ["state"],
            registry=self.registry,
        )
        self.index_corrupt = Counter(
            "hmpf_index_corrupt",
            "index versions the background check found corrupt",
            registry=self.registry,
        )
        self.reloads = Counter(
            "hmpf_index_reloads",
            "reloads that switched the loaded index version",
            ["trigger"],
            registry=self.registry,
        )
        self.reload_failures = Counter(
            "hmpf_index_reload_failures",
            "reloads that failed (the loaded version stayed in service)",
            ["trigger"],
            registry=self.registry,
        )
        self.sequence_frames = Counter(
            "hmpf_sequence_frames",
            "frames answered in sequence mode, by track status",
            ["status"],
            registry=self.registry,
        )
        self.sequence_resets = Counter(
            "hmpf_sequence_resets",
            "tracks restarted because their token was not trusted",
            ["reason"],
            registry=self.registry,
        )
        self.sequence_refused = Counter(
            "hmpf_sequence_refused",
            "requests refused for their track token (422 invalid_track)",
            ["reason"],
            registry=self.registry,
        )
        self.sequence_answers = Counter(
            "hmpf_sequence_answers",
            "sequence-mode answers, by whether the estimate was locked (accepted)",
            ["locked"],
            registry=self.registry,
        )
        self.sequence_update = Histogram(
            "hmpf_sequence_update_seconds",
            "sequence filter time per frame (update, token)",
            buckets=_FILTER_BUCKETS,
            registry=self.registry,
        )
        self.experience_recorded = Counter(
            "hmpf_experience_recorded",
            "frames appended to the experience log",
            registry=self.registry,
        )
        self.experience_dropped = Counter(
            "hmpf_experience_dropped",
            "frames meant for the experience log that are not in it: queue_full, error "
            "(open or write failed), bound (deleted with the oldest segments)",
            ["reason"],
            registry=self.registry,
        )
        self.experience_queue = Gauge(
            "hmpf_experience_queue", "frames waiting to be recorded", registry=self.registry
        )
        self.experience_bytes = Gauge(
            "hmpf_experience_bytes", "the experience log's size on disk", registry=self.registry
        )
        self.experience_lead_bytes = Gauge(
            "hmpf_experience_lead_bytes",
            "images held in memory as the vehicles' lead-in frames",
            registry=self.registry,
        )
        # Every series from the start (at 0), so that rates and alerts need no special case.
        for reason in DROP_REASONS:
            self.experience_dropped.labels(reason)
        for status in STATUSES:
            self.sequence_frames.labels(status)
        for reason in RESET_REASONS:
            self.sequence_resets.labels(reason)
        for refusal in REFUSALS:
            self.sequence_refused.labels(refusal)
        for locked in ("true", "false"):
            self.sequence_answers.labels(locked)
        for trigger in RELOAD_TRIGGERS:
            self.reloads.labels(trigger)
            self.reload_failures.labels(trigger)
        for state in VERIFICATION_STATES:
            self.index_verification.labels(state)

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
        """``hmpf_index_info``: 1 for ``version`` only (also called at each scrape)."""
        if version == self._version:
            return
        if self._version is not None:
            with contextlib.suppress(KeyError):  # a concurrent call removed it
                self.index.remove(self._version)
        self.index.labels(version).set(1)
        self._version = version

    def set_verification(self, state: str) -> None:
        """``hmpf_index_verification``: 1 for ``state``, 0 for the others."""
        for s in VERIFICATION_STATES:
            self.index_verification.labels(s).set(int(s == state))

    def response(self) -> Response:
        return Response(generate_latest(self.registry), media_type=CONTENT_TYPE_LATEST)
