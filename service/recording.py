"""Recording confidently localised frames into the experience log, off the request's path.

With the setting ``experience_log`` (off by default) the localisation routes offer every
answer to the app's :class:`Recorder` once it is final (in sequence mode: after the filter,
so the sequence answer is what counts). A frame is recorded when its answer's match is
``accepted`` with ``p_correct >= experience_min_p_correct`` and the answer's mode (its
``match_source``: ``sequence`` or ``single``) is in ``experience_modes``; an answer without
``p_correct`` (a version without a confidence model) never is. The record holds the
uploaded bytes, the matched place and its name, ``p_correct``, the vehicle's id (``""``
without one), the frame's timestamp (the request's, else when it was received), the
index version that answered and the mode (:class:`hmpf.experience_log.Record`), and, with
``experience_features`` (on by default), the frame's features as that version's methods
extracted them to answer it (:func:`hmpf.features.pack_features`, packed on the recorder's
thread), which a merge into the same version reads instead of extracting them again.

The request only puts the frame on a bounded queue: :meth:`Recorder.offer` never waits and
never raises. One background thread appends to the log (:class:`~hmpf.experience_log.
ExperienceLog`: fsynced in batches, bounded in size). When the queue is full (a slow or
stuck disk, a prune holding the log) or the log cannot be opened or written (a full disk,
a folder the service may not write, another service writing the same log) the frame is
dropped and counted (``hmpf_experience_dropped_total{reason}``), the cause logged at most
once a minute, and the log is opened again every few seconds: the answers are never slower
or failed for it. At shutdown the queued frames are written and the log is flushed and
closed (:meth:`Recorder.stop`).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from hmpf.experience_log import ExperienceLog, ExperienceLogError
from hmpf.features import pack_features
from hmpf.methods import Method
from service.metrics import Metrics
from service.schemas import LocalizeResponse
from service.settings import Settings

__all__ = ["Frame", "Recorder", "recorded_mode"]

log = logging.getLogger("hmpf.service")
#: Seconds between tries to open a log that could not be opened.
REOPEN_S = 5.0
#: Seconds between two log lines about the same kind of failure.
WARN_EVERY_S = 60.0
#: What tells the thread to finish (after the frames queued before it).
_STOP: Any = object()


@dataclass(frozen=True)
class Frame:
    """A frame on its way to the log (the record's fields the service knows)."""

    image: bytes
    content_type: str | None
    place: int
    place_name: str
    index_version: str
    p_correct: float
    vehicle: str
    timestamp: float
    mode: str
    received: float
    features: Mapping[str, Any] | None = None
    methods: Mapping[str, Method] | None = None


def recorded_mode(answer: LocalizeResponse, settings: Settings) -> str | None:
    """The mode ``answer`` is recorded under, or None when it is not to be recorded."""
    m = answer.match
    if m is None or not m.accepted or m.p_correct is None:
        return None
    if not m.p_correct >= settings.experience_min_p_correct:
        return None
    mode = answer.match_source
    return mode if mode in settings.experience_modes else None


class Recorder:
    """The app's experience recorder: a bounded queue and the thread that writes the log.

    Build it with :meth:`for_settings` (None when recording is off), then :meth:`start`;
    :meth:`offer` from the routes; :meth:`stop` at shutdown.
    """

    def __init__(self, settings: Settings, metrics: Metrics) -> None:
        if settings.experience_log is None:
            raise ValueError("recording is off: no experience_log")
        self.settings = settings
        self.metrics = metrics
        self.path = settings.experience_log
        self._queue: queue.Queue[Any] = queue.Queue(settings.experience_queue)
        self._thread = threading.Thread(target=self._run, name="hmpf-recorder", daemon=True)
        self._log: ExperienceLog | None = None
        self._open_at = 0.0  # monotonic time of the next try to open the log
        self._warned: dict[str, float] = {}
        self._bound_seen = 0

    @classmethod
    def for_settings(cls, settings: Settings, metrics: Metrics) -> Recorder | None:
        return None if settings.experience_log is None else cls(settings, metrics)

    def start(self) -> None:
        """Start the thread; it opens the log (a failure is logged and tried again later;
        a prune holding the log delays it, never the service's start)."""
        self._thread.start()
        modes = ", ".join(self.settings.experience_modes)
        log.info(
            "recording accepted frames (%s, p_correct >= %g) to the experience log %s",
            modes,
            self.settings.experience_min_p_correct,
            self.path,
        )

    def offer(
        self,
        answer: LocalizeResponse,
        image: bytes,
        content_type: str | None,
        vehicle_id: str | None,
        timestamp: float | None,
        received: float,
        features: Mapping[str, Any] | None = None,
        methods: Mapping[str, Method] | None = None,
    ) -> bool:
        """Queue the frame when its answer is to be recorded; whether it was queued.
        ``features``, ``methods``: the frame's features and the methods that extracted
        them (packed into the record on the recorder's thread; None: recorded without).

        Never waits and never raises: a full queue, or anything unexpected, drops the frame
        (counted), so that the request it belongs to is answered as if nothing happened.
        """
        try:
            mode = recorded_mode(answer, self.settings)
            if mode is None:
                return False
            match = answer.match
            assert match is not None and match.p_correct is not None  # recorded_mode checked
            frame = Frame(
                image=image,
                content_type=content_type,
                place=match.reference_id,
                place_name=match.name,
                index_version=answer.index_version,
                p_correct=match.p_correct,
                vehicle=vehicle_id or "",
                timestamp=received if timestamp is None else timestamp,
                mode=mode,
                received=received,
                features=features if methods is not None else None,
                methods=methods,
            )
            self._queue.put_nowait(frame)
        except queue.Full:
            self.metrics.experience_dropped.labels("queue_full").inc()
            self._warn("queue_full", "experience log: the queue is full; frames are dropped")
            return False
        except Exception:  # a bug must not fail the answer: logged, counted
            log.exception("experience log: a frame could not be queued")
            self.metrics.experience_dropped.labels("error").inc()
            return False
        self.metrics.experience_queue.set(self._queue.qsize())
        return True

    def stop(self, timeout_s: float = 10.0) -> None:
        """Write the frames queued so far, flush and close the log; waits ``timeout_s`` at
        most (a stuck disk: the frames left are lost, as with a kill)."""
        if not self._thread.is_alive():
            self._close()
            return
        deadline = time.monotonic() + timeout_s
        try:
            self._queue.put(_STOP, timeout=timeout_s)
        except queue.Full:
            pass
        self._thread.join(max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            log.error(
                "experience log: %d frames were not written by shutdown (the disk did not "
                "answer in %g s)",
                self._queue.qsize(),
                timeout_s,
            )

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        tick = min(self.settings.experience_sync_s, 1.0)
        self._ensure_log()
        while True:
            try:
                item = self._queue.get(timeout=tick)
            except queue.Empty:
                item = None
            self.metrics.experience_queue.set(self._queue.qsize())
            if item is _STOP:
                break
            if item is not None:
                self._write(item)
            self._sync()
        self._close()

    def _write(self, frame: Frame) -> None:
        writer = self._ensure_log()
        if writer is None:
            self.metrics.experience_dropped.labels("error").inc()
            return
        packed = None
        if frame.features is not None and frame.methods is not None:
            try:
                packed = pack_features(frame.methods, frame.features)
            except Exception as exc:  # never the thread's end: the frame goes without them
                self._warn("features", "experience log %s: features not recorded: %s", exc)
        try:
            writer.append(
                frame.image,
                content_type=frame.content_type,
                place=frame.place,
                place_name=frame.place_name,
                index_version=frame.index_version,
                p_correct=frame.p_correct,
                vehicle=frame.vehicle,
                timestamp=frame.timestamp,
                mode=frame.mode,
                received=frame.received,
                features=packed,
            )
        except ValueError as exc:  # a field the log refuses (e.g. an image over its bound)
            self.metrics.experience_dropped.labels("error").inc()
            self._warn("frame", "experience log %s: a frame was refused: %s", exc)
            return
        except (OSError, ExperienceLogError) as exc:
            # Closed and opened again later: a full disk may drain, a removed folder is
            # made again; meanwhile the frames are dropped without touching the disk.
            self.metrics.experience_dropped.labels("error").inc()
            self._warn("write", "experience log %s: a frame could not be written: %s", exc)
            self._close()
            self._open_at = time.monotonic() + REOPEN_S
            return
        self.metrics.experience_recorded.inc()
        self._account(writer)

    def _sync(self) -> None:
        if self._log is None:
            return
        try:
            self._log.maybe_flush()
        except OSError as exc:
            self._warn("sync", "experience log %s: fsync failed: %s", exc)

    def _ensure_log(self) -> ExperienceLog | None:
        """The open log, opening it when due; None while it cannot be opened."""
        if self._log is not None or time.monotonic() < self._open_at:
            return self._log
        s = self.settings
        try:
            self._log = ExperienceLog(
                self.path,
                max_bytes=s.experience_max_bytes,
                segment_bytes=s.experience_segment_bytes,
                sync_every=s.experience_sync_every,
                sync_interval_s=s.experience_sync_s,
            )
        except (OSError, ExperienceLogError) as exc:
            self._open_at = time.monotonic() + REOPEN_S
            self._warn("open", "experience log %s cannot be opened; frames are dropped: %s", exc)
            return None
        self._bound_seen = 0
        self._account(self._log)
        return self._log

    def _account(self, writer: ExperienceLog) -> None:
        """The metrics of what the writer did: frames the bound deleted, the log's size."""
        if writer.dropped > self._bound_seen:
            self.metrics.experience_dropped.labels("bound").inc(writer.dropped - self._bound_seen)
            self._bound_seen = writer.dropped
        self.metrics.experience_bytes.set(writer.total_bytes)

    def _close(self) -> None:
        if self._log is None:
            return
        try:
            self._log.close()
        except OSError as exc:
            self._warn("close", "experience log %s: closing failed: %s", exc)
        self._log = None

    def _warn(self, kind: str, message: str, exc: BaseException | None = None) -> None:
        """Log ``message`` at most once a minute per ``kind`` (a full disk fails every frame)."""
        now = time.monotonic()
        if now - self._warned.get(kind, -math.inf) < WARN_EVERY_S:
            return
        self._warned[kind] = now
        if exc is None:
            log.error(message)
        else:
            log.error(message, self.path, exc)
