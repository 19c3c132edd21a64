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

A lock's lead-in (``experience_lead_frames``, 2 by default; 0: off): in sequence mode the
recorder keeps each vehicle's last frames that were not recorded since its track started or
it was last answered off the map (in memory, bounded per vehicle and by
``experience_lead_bytes`` overall: :class:`Leads`). When the vehicle's next frame is
recorded, those taken at most :data:`LEAD_MAX_GAP_S` before it by the same index version are
recorded first, as ``lead`` frames (their own answer's place and ``p_correct``, no
features; only when the queue has room for them and the frame), into ``sequence`` records
only (any recorded frame closes the vehicle); a merge places them from the recorded frames
after them (:func:`indexer.experiences.place_leads`). The places a vehicle passes before
the filter is sure, the same places on every drive that starts at one depot, get
experiences too; a lock lost and found again on the map records no lead-in. Replicas keep
their own: a vehicle whose frames reach several loses some lead-ins, nothing else. A
frame's time is the request's timestamp, else when it was received: a vehicle should send
timestamps always or never (a batch's frames share one received time, so none leads into
another).

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
from collections import OrderedDict, deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from hmpf.experience_log import MAX_GAP_S, ExperienceLog, ExperienceLogError
from hmpf.features import pack_features
from hmpf.methods import Method
from service.metrics import Metrics
from service.schemas import LocalizeResponse
from service.settings import Settings

__all__ = ["LEAD_MAX_GAP_S", "Frame", "Leads", "Recorder", "recorded_mode"]

log = logging.getLogger("hmpf.service")
#: Seconds between tries to open a log that could not be opened.
REOPEN_S = 5.0
#: Seconds between two log lines about the same kind of failure.
WARN_EVERY_S = 60.0
#: What tells the thread to finish (after the frames queued before it).
_STOP: Any = object()
#: The longest time (seconds, by the frames' timestamps) from a lead-in frame to the recorded
#: frame it leads into (the log's bound, which the merge reads its frames by too).
LEAD_MAX_GAP_S = MAX_GAP_S
#: What a held frame counts for beyond its image's bytes (its fields, the vehicle's entry).
_HELD_OVERHEAD = 1024


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


class Leads:
    """Each vehicle's lead-in: its last frames not recorded while it is *open*.

    A vehicle is open from its track's start (a frame sent without a track, or a track
    reset) and from an answer that puts it off the map, until its next recorded frame, which
    takes the frames held (:meth:`take`) and closes it. So the frames before a lock are kept
    where the filter starts from nothing (a drive's start, a vehicle joining the route), and
    not where a lock is lost and found again on the map (those are the frames the filter
    found hardest, of places a lock covers on other drives). A vehicle this service has not
    seen start is closed.

    At most ``frames`` per vehicle (the newest) and ``max_bytes`` in all (each frame's image
    plus a kilobyte, each open vehicle a kilobyte): over it, the vehicle heard from longest
    ago is closed and loses its frames. Thread-safe; every call is a few dictionary
    operations (it runs on the request's path).
    """

    def __init__(self, frames: int, max_bytes: int) -> None:
        self.frames, self.max_bytes = frames, max_bytes
        self._open: OrderedDict[str, deque[Frame]] = OrderedDict()
        self._lock = threading.Lock()
        self.bytes = 0

    def open(self, vehicle: str) -> None:
        """Open ``vehicle`` (its track starts, or it is off the map): its frames held so far
        are dropped."""
        if self.frames == 0:
            return
        with self._lock:
            self._close(vehicle)
            self._open[vehicle] = deque()
            self.bytes += _HELD_OVERHEAD
            self._bound()

    def keep(self, frame: Frame) -> None:
        """Hold ``frame`` (mode ``lead``) as its vehicle's newest, if the vehicle is open."""
        if _held_size(frame) + _HELD_OVERHEAD > self.max_bytes:  # with its vehicle's entry
            with self._lock:
                self._close(frame.vehicle)
            return
        with self._lock:
            held = self._open.pop(frame.vehicle, None)
            if held is None:
                return
            self._open[frame.vehicle] = held  # the most recently heard from last
            held.append(frame)
            self.bytes += _held_size(frame)
            while len(held) > self.frames:
                self.bytes -= _held_size(held.popleft())
            self._bound()

    def take(self, frame: Frame) -> list[Frame]:
        """The held frames of ``frame``'s vehicle that lead into it (the same index version,
        taken before it, at most :data:`LEAD_MAX_GAP_S` earlier), oldest first; the vehicle
        is closed."""
        with self._lock:
            held = self._close(frame.vehicle)
        return [
            f
            for f in held
            if f.index_version == frame.index_version
            and 0.0 < frame.timestamp - f.timestamp <= LEAD_MAX_GAP_S
        ]

    def _bound(self) -> None:
        while self.bytes > self.max_bytes and self._open:
            self._close(next(iter(self._open)))

    def _close(self, vehicle: str) -> deque[Frame]:
        held = self._open.pop(vehicle, None)
        if held is None:
            return deque()
        self.bytes -= _HELD_OVERHEAD + sum(map(_held_size, held))
        return held


def _frame(
    answer: LocalizeResponse,
    mode: str,
    image: bytes,
    content_type: str | None,
    stamp: tuple[str, float, float],
    features: Mapping[str, Any] | None,
    methods: Mapping[str, Method] | None,
) -> Frame:
    """The frame of an answer with a match, recorded under ``mode`` (``stamp``: its vehicle,
    ``""`` without one, its time and when it was received; a lead frame's ``p_correct`` is
    its own answer's, 0 without one)."""
    match = answer.match
    assert match is not None  # recorded answers and lead frames have one
    vehicle, timestamp, received = stamp
    return Frame(
        image=image,
        content_type=content_type,
        place=match.reference_id,
        place_name=match.name,
        index_version=answer.index_version,
        p_correct=0.0 if match.p_correct is None else match.p_correct,
        vehicle=vehicle,
        timestamp=timestamp,
        mode=mode,
        received=received,
        features=features,
        methods=methods,
    )


def _starts(answer: LocalizeResponse) -> bool:
    """Whether ``answer`` starts its vehicle's track (its first frame, or a reset)."""
    return answer.sequence is not None and answer.sequence.status in ("started", "reset")


def _held_size(frame: Frame) -> int:
    return len(frame.image) + _HELD_OVERHEAD


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
        self.leads = Leads(settings.experience_lead_frames, settings.experience_lead_bytes)
        # lead-ins lead into sequence-mode records only
        self._leads_recorded = "sequence" in settings.experience_modes
        metrics.experience_lead_bytes.set_function(lambda: self.leads.bytes)

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
            stamp = (vehicle_id or "", received if timestamp is None else timestamp, received)
            if mode is None:
                if vehicle_id is not None and self._leads_recorded:
                    self._hold(answer, image, content_type, stamp)
                return False
            kept = features if methods is not None else None
            frame = _frame(answer, mode, image, content_type, stamp, kept, methods)
            if vehicle_id is not None:  # any recorded frame closes the vehicle
                leads = self.leads.take(frame)
                if mode == "sequence":
                    self._queue_leads(leads)
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

    def _queue_leads(self, leads: list[Frame]) -> None:
        """Queue a recorded frame's lead-in frames, before it, when the queue has room for
        them and the frame (else they are dropped, counted: the recorded frame comes
        first)."""
        if self._queue.maxsize - self._queue.qsize() <= len(leads):
            self.metrics.experience_dropped.labels("queue_full").inc(len(leads))
            return
        for lead in leads:
            try:
                self._queue.put_nowait(lead)
            except queue.Full:  # another request took the room meanwhile
                self.metrics.experience_dropped.labels("queue_full").inc()

    def _hold(
        self,
        answer: LocalizeResponse,
        image: bytes,
        content_type: str | None,
        stamp: tuple[str, float, float],
    ) -> None:
        """Keep a sequence-mode frame that was not recorded as a possible lead-in (without its
        features, :class:`Leads`): a track's start opens the vehicle, and so does an answer
        off the map (which is no lead-in itself, nor is an answer without a match)."""
        report = answer.sequence
        if report is None:
            return
        if report.off_map or _starts(answer):
            self.leads.open(stamp[0])
        if not report.off_map and answer.match is not None:
            self.leads.keep(_frame(answer, "lead", image, content_type, stamp, None, None))

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
