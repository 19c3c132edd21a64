"""Sequence mode for the localisation routes: a vehicle's track token in, the filter over its
frames, the new token out.

A request with a ``vehicle_id`` is in sequence mode. Before its images run,
:meth:`Tracker.open` checks the ``track`` it brought (422 ``invalid_track`` for a token that is
not ours or not the vehicle's); after they are answered, :meth:`Tracker.follow` runs the
filter over the answers in order (:func:`service.track.follow`, about half a millisecond per
frame) and adds each frame's report and the new token (:func:`service.answer.with_sequence`).
Nothing is kept between requests: the token is the vehicle's whole track.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from hmpf.acceptance import Decision
from hmpf.errors import ConfigError
from hmpf.sequence import Estimate
from service.answer import sequence_decision, with_sequence
from service.engine import Loaded
from service.errors import ApiError
from service.metrics import Metrics
from service.query import ImageQuery
from service.schemas import LocalizeParams, LocalizeResponse
from service.settings import Settings
from service.track import (
    KEY_FILE,
    TokenCodec,
    Track,
    TrackRefused,
    follow,
    load_or_create_key,
    vehicle_digest,
)

__all__ = ["SEQUENCE_RETRY_AFTER_S", "Tracker", "VehicleRequest"]

log = logging.getLogger("hmpf.service")
#: Retry-After (seconds) of a 503 ``sequence_unavailable``: the key is tried again on every
#: request, so sequence mode comes back as soon as the operator fixes the key file.
SEQUENCE_RETRY_AFTER_S = 30


@dataclass(frozen=True)
class VehicleRequest:
    """A request's sequence-mode fields, its token checked.

    Attributes:
        vehicle: :func:`~service.track.vehicle_digest` of the ``vehicle_id``.
        token: the ``track`` as sent (handed back unchanged for a frame out of order).
        prev: the track it holds, or None on the vehicle's first frame.
        timestamp: the frame's capture time (single requests only).
    """

    vehicle: bytes
    token: str | None
    prev: Track | None
    timestamp: float | None


class _Decider:
    """The one policy's decision on a frame's estimate (:func:`sequence_decision`): whether
    the next frame is held (:attr:`~hmpf.acceptance.Decision.holds`: accepted, or kept
    through a frame the stay threshold's evidence floor held back) is recorded in the
    vehicle's track (``follow``'s ``accept``, the hysteresis of the next frame), and the
    decision is kept for the frame's answer, so both say the same."""

    def __init__(self, loaded: Loaded, query: ImageQuery) -> None:
        self.loaded, self.query = loaded, query
        self.decision: Decision | None = None

    def __call__(self, estimate: Estimate) -> bool:
        self.decision = sequence_decision(self.loaded, estimate, self.query.result)
        return self.decision.holds


def _refused(exc: TrackRefused) -> ApiError:
    return ApiError(422, "invalid_track", f"{exc}; send the frame without track to start a new one")


class Tracker:
    """Checks and issues track tokens for one app (the signing key is read on first use)."""

    def __init__(self, settings: Settings, metrics: Metrics) -> None:
        self.settings = settings
        self.metrics = metrics
        self._codec: TokenCodec | None = None
        self._lock = threading.Lock()

    @property
    def codec(self) -> TokenCodec:
        """The token codec with the service's key (setting, else the key file).

        Raises:
            ApiError: 503 ``sequence_unavailable`` (with Retry-After) when there is no key and
                the key file cannot be created (e.g. a read-only index folder); tried again
                next time. The answer names no path (the log does).
        """
        with self._lock:
            if self._codec is None:
                self._codec = TokenCodec(self._key())
            return self._codec

    def _key(self) -> bytes:
        s = self.settings
        if s.sequence_key is not None:
            return s.sequence_key.get_secret_value().encode()
        path = s.sequence_key_file or Path(s.index) / KEY_FILE
        try:
            return load_or_create_key(path)
        except ConfigError as exc:
            # The path is the operator's to know (the log), never a client's (the answer).
            log.error("sequence mode unavailable: %s", exc)
            raise ApiError(
                503,
                "sequence_unavailable",
                "sequence mode is unavailable: the service has no sequence key (the operator "
                "sets HMPF_SEQUENCE_KEY, or HMPF_SEQUENCE_KEY_FILE to a writable file; the "
                "service log says what failed); frames without vehicle_id are answered, retry "
                "sequence mode later",
                {"Retry-After": str(SEQUENCE_RETRY_AFTER_S)},
            ) from None

    def open(self, params: LocalizeParams) -> VehicleRequest | None:
        """The request's sequence mode (None without a ``vehicle_id``), its token checked.

        Raises:
            ApiError: 422 ``invalid_track`` for a token that does not decode, is not signed
                by this service's key (or was altered) or belongs to another vehicle.
        """
        if params.vehicle_id is None:
            return None
        codec = self.codec
        prev = None
        if params.track is not None:
            try:
                prev = codec.decode(params.track, params.vehicle_id)
            except TrackRefused as exc:
                self.metrics.sequence_refused.labels(exc.reason).inc()
                raise _refused(exc) from None
        return VehicleRequest(
            vehicle_digest(params.vehicle_id), params.track, prev, params.timestamp
        )

    def follow(
        self,
        request: VehicleRequest,
        answers: Sequence[LocalizeResponse | None],
        queries: Sequence[ImageQuery],
    ) -> tuple[list[LocalizeResponse | None], str | None]:
        """Run the filter over a request's answers, in order.

        Args:
            request: from :meth:`open`.
            answers: per frame its answer, or None for a frame that failed (skipped; the
                next frame counts it as dropped).
            queries: the frames' queries (their evidence and version).

        Returns:
            (the answers with their sequence reports, None where a frame failed; the token
            for the vehicle's next request, None when no frame was answered and none was
            given).
        """
        codec, token, prev = self.codec, request.token, request.prev
        out: list[LocalizeResponse | None] = []
        dropped = 0
        for answer, query in zip(answers, queries, strict=True):
            if answer is None or query.loaded is None or query.evidence is None:
                dropped += 1
                out.append(None)
                continue
            t = time.perf_counter()
            loaded = query.loaded
            accept = _Decider(loaded, query)
            try:
                step = follow(
                    loaded.sequence,
                    loaded.binding,
                    prev,
                    query.evidence,
                    vehicle=request.vehicle,
                    timestamp=request.timestamp,
                    now=time.time(),
                    max_age_s=self.settings.track_max_age_s,
                    dropped=dropped,
                    accept=accept,
                )
            except TrackRefused as exc:
                self.metrics.sequence_refused.labels(exc.reason).inc()
                raise _refused(exc) from None
            except (ArithmeticError, ValueError) as exc:
                # A bug's last line of defence: a track the filter cannot continue is refused
                # (the vehicle starts a new one on a 422), never a 500 on every later frame.
                log.warning("track of a vehicle refused: the filter failed on it", exc_info=exc)
                self.metrics.sequence_refused.labels("malformed").inc()
                raise _refused(TrackRefused("malformed", "track: cannot be continued")) from None
            if step.status != "out_of_order":
                prev, token = step.track, codec.encode(step.track)
            dropped = 0
            assert token is not None  # issued above unless out of order (which had one)
            answer = with_sequence(answer, loaded, step, token, query.result, accept.decision)
            seconds = time.perf_counter() - t
            answer.timing_ms["sequence"] = seconds * 1e3
            locked = answer.sequence is not None and answer.sequence.locked
            self._count(step.status, step.reason, locked, seconds)
            out.append(answer)
        return out, token

    def _count(self, status: str, reason: str | None, locked: bool, seconds: float) -> None:
        m = self.metrics
        m.sequence_frames.labels(status).inc()
        if reason is not None:
            m.sequence_resets.labels(reason).inc()
        m.sequence_answers.labels("true" if locked else "false").inc()
        m.sequence_update.observe(seconds)
