"""Sequence mode's pure parts: the signed track token a vehicle carries, and one filter step.

The server keeps no state per vehicle. Each answer in sequence mode carries the vehicle's
filter state as a *track token*, signed by the server; the vehicle sends it back with its next
frame, to any replica. The token (base64url, no padding) is ``payload || mac``:

===========  =====  ========================================================================
field        bytes  meaning
===========  =====  ========================================================================
format       1      :data:`TOKEN_FORMAT`
binding      8      the index version it was made on (manifest, config, filter settings)
vehicle      8      sha256 of the ``vehicle_id`` (a token is valid for one vehicle only)
issued_at    8      server time (epoch seconds) it was issued
timestamp    8      the frame's capture time (NaN: not given)
interval     8      the estimated time between two frames (NaN: not known yet)
state        ...    :meth:`hmpf.sequence.SequenceFilter.pack` (at most 64 hypotheses)
mac          32     HMAC-SHA256 of the payload with the service's sequence key
===========  =====  ========================================================================

About 480 bytes, 640 characters (the state: format 5, with the "not in the map" mass, the
last estimate and the caller's last acceptance; a token of an older state format was made
with other filter settings, so its binding differs and the track restarts, ``index_changed``).
The key is a setting (``sequence_key``) or, by default, a random key in a file inside the
index folder (:func:`load_or_create_key`), so every replica on the same index, and a
restarted server, accept each other's tokens.

:func:`follow` is one frame of a vehicle: it checks the token's binding and age, turns the
frame's timestamp into the number of frames moved (:func:`frame_steps`) and runs the filter;
with the caller's acceptance rule (``accept``) it records the decision in the state
(:meth:`~hmpf.sequence.SequenceFilter.hold`), so the next frame's estimate knows it
(:attr:`~hmpf.sequence.Estimate.held`).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import hashlib
import hmac
import json
import math
import os
import secrets
import struct
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hmpf.api import MAX_TOKEN_CHARS
from hmpf.errors import ConfigError, HmpfError
from hmpf.sequence import (
    Estimate,
    Evidence,
    FilterParams,
    SequenceFilter,
    StateError,
)

__all__ = [
    "KEY_FILE",
    "MAX_STEPS",
    "MAX_TOKEN_CHARS",
    "MIN_INTERVAL_S",
    "NO_EVIDENCE",
    "REFUSALS",
    "RESET_REASONS",
    "STATUSES",
    "TOKEN_FORMAT",
    "Step",
    "TokenCodec",
    "Track",
    "TrackRefused",
    "binding_digest",
    "follow",
    "frame_steps",
    "load_or_create_key",
    "vehicle_digest",
]

TOKEN_FORMAT = 1
#: The default key file, inside the index folder (next to ``CURRENT``).
KEY_FILE = ".sequence-key"
#: Hypotheses a token keeps (the rest of the belief joins the even background).
KEEP = 64
_HEAD = struct.Struct("<B8s8sddd")
_MAC = 32

Status = Literal["started", "tracking", "reset", "out_of_order"]
ResetReason = Literal["expired", "index_changed"]
Refusal = Literal["malformed", "signature", "vehicle"]
#: Every value of a sequence answer's ``status``, reset ``reason`` and refusal reason (the
#: only label values the metrics use).
STATUSES: tuple[Status, ...] = ("started", "tracking", "reset", "out_of_order")
RESET_REASONS: tuple[ResetReason, ...] = ("expired", "index_changed")
REFUSALS: tuple[Refusal, ...] = ("malformed", "signature", "vehicle")
#: A frame that brings no evidence (a GPS prior that leaves no reference): motion only.
NO_EVIDENCE = Evidence((), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))


class TrackRefused(HmpfError):
    """A track token that is not one of ours for this vehicle (``reason``: a :data:`REFUSALS`)."""

    def __init__(self, reason: Refusal, message: str) -> None:
        super().__init__(message)
        self.reason: Refusal = reason


# -- the key -----------------------------------------------------------------------------------
def load_or_create_key(path: Path) -> bytes:
    """The 32-byte key in ``path`` (64 hex digits), created first if missing.

    Creation is atomic and race-free between replicas: the key is written to a private
    temporary file (mode 0600), fsynced, and hard-linked to ``path``, which fails if another
    process got there first, whose key is then read.

    Raises:
        ConfigError: the file cannot be read or created, or holds no key.
    """
    if not path.exists():
        try:
            _create_key(path)
        except OSError as exc:
            raise ConfigError(
                f"cannot create the sequence key file {str(path)!r} ({exc.strerror}); set "
                "HMPF_SEQUENCE_KEY, or HMPF_SEQUENCE_KEY_FILE to a writable path"
            ) from None
    try:
        text = path.read_text().strip()
    except OSError as exc:
        raise ConfigError(
            f"cannot read the sequence key file {str(path)!r}: {exc.strerror}"
        ) from None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != 32:
        raise ConfigError(f"{path}: expected a sequence key of 64 hex digits; delete the file")
    return key


def _create_key(path: Path) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32) + "\n")
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(FileExistsError):  # another replica's key won
            os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


# -- the token ---------------------------------------------------------------------------------
def vehicle_digest(vehicle_id: str) -> bytes:
    """The 8 bytes of a token that name its vehicle."""
    return hashlib.sha256(b"hmpf-vehicle\0" + vehicle_id.encode()).digest()[:8]


@dataclass(frozen=True)
class Track:
    """What a token carries (see the module docstring)."""

    binding: bytes
    vehicle: bytes
    issued_at: float
    timestamp: float
    interval: float
    state: bytes

    def payload(self) -> bytes:
        head = _HEAD.pack(
            TOKEN_FORMAT, self.binding, self.vehicle, self.issued_at, self.timestamp, self.interval
        )
        return head + self.state


class TokenCodec:
    """Signs tracks into tokens and checks tokens (HMAC-SHA256, constant-time compare)."""

    def __init__(self, key: bytes) -> None:
        if len(key) < 16:
            raise ConfigError("the sequence key needs at least 16 bytes")
        self._key = key

    def _mac(self, payload: bytes) -> bytes:
        return hmac.new(self._key, payload, hashlib.sha256).digest()

    def encode(self, track: Track) -> str:
        payload = track.payload()
        return base64.urlsafe_b64encode(payload + self._mac(payload)).rstrip(b"=").decode()

    def decode(self, token: str, vehicle_id: str) -> Track:
        """The track in ``token``, checked: ours (signature), for ``vehicle_id``.

        Raises:
            TrackRefused: ``malformed`` (not a token), ``signature`` (not signed by this
                service's key, or altered) or ``vehicle`` (another vehicle's token).
        """
        raw = _b64decode(token)
        if raw is None or len(raw) < _HEAD.size + _MAC or raw[0] != TOKEN_FORMAT:
            raise TrackRefused("malformed", "track: not a track token of this service")
        payload, mac = raw[:-_MAC], raw[-_MAC:]
        if not hmac.compare_digest(mac, self._mac(payload)):
            raise TrackRefused(
                "signature", "track: bad signature (altered, or signed with another key)"
            )
        _, binding, vehicle, issued, ts, interval = _HEAD.unpack_from(payload)
        if not hmac.compare_digest(vehicle, vehicle_digest(vehicle_id)):
            raise TrackRefused("vehicle", "track: this token belongs to another vehicle_id")
        return Track(binding, vehicle, issued, ts, interval, payload[_HEAD.size :])


def _b64decode(token: str) -> bytes | None:
    """Strict base64url without padding; None for anything else."""
    try:
        raw = token.encode("ascii")
        out = base64.urlsafe_b64decode(raw + b"=" * (-len(raw) % 4))
    except (UnicodeEncodeError, binascii.Error, ValueError):
        return None
    # Canonical form only (no padding, no stray bits): one token, one spelling.
    return out if base64.urlsafe_b64encode(out).rstrip(b"=") == raw else None


# -- one index version's filter ------------------------------------------------------------------
def binding_digest(manifest: dict[str, Any], params: FilterParams) -> bytes:
    """8 bytes naming an index version and the filter settings a state is valid for."""
    text = json.dumps({"manifest": manifest, "sequence": asdict(params)}, sort_keys=True)
    return hashlib.sha256(text.encode()).digest()[:8]


# -- one frame ---------------------------------------------------------------------------------
#: Weight of the newest frame gap in the running estimate of the frame interval.
_INTERVAL_WEIGHT = 0.25
#: Largest number of frames one step may cover (far beyond any filter's ``max_gap``).
MAX_STEPS = 10_000
#: The shortest time between two frames (seconds): frames closer than this are the same
#: instant, and a learned interval below it (no camera's) is not kept.
MIN_INTERVAL_S = 1e-6


def frame_steps(dt: float, interval: float) -> tuple[int, float]:
    """Frames moved since the last frame, from the time between them, and the new interval.

    Defined for every float pair (NaN, infinities, subnormals and negatives included): a
    token's interval is whatever an earlier frame's timestamps made it, so nothing here may
    raise or carry on an interval that the next frame could not use.

    Args:
        dt: seconds since the previous frame (NaN: unknown; >= 0).
        interval: the estimated seconds between frames (NaN: not known yet).

    Returns:
        (steps, interval): 1 when the time is unknown or the first interval is being
        learned; 0 for the same instant (less than :data:`MIN_INTERVAL_S` apart); else
        ``round(dt / interval)`` (at least 1, at most :data:`MAX_STEPS`), the frames dropped
        in between being ``steps - 1``. The interval follows the vehicle's rate: a running
        mean of ``dt / steps``, restarted at ``dt`` when a frame comes much sooner than
        expected (the first gap measured was itself a gap). The interval returned is NaN
        (not known) or a finite number >= :data:`MIN_INTERVAL_S`.
    """
    known = math.isfinite(interval) and MIN_INTERVAL_S <= interval
    if not known:
        interval = math.nan  # not known (or not a camera's: less than a microsecond)
    if not math.isfinite(dt):
        return 1, interval
    if dt < MIN_INTERVAL_S:  # negative, zero or below a microsecond: the same instant
        return 0, interval
    if not known or dt < 0.75 * interval:
        return 1, dt
    # dt / interval is finite or +inf (both positive, the interval not tiny): capped first,
    # so that round() never sees an infinity.
    steps = max(1, round(min(dt / interval, MAX_STEPS)))
    new = (1 - _INTERVAL_WEIGHT) * interval + _INTERVAL_WEIGHT * (dt / steps)
    return steps, new if math.isfinite(new) else interval


@dataclass(frozen=True)
class Step:
    """What one frame did to a vehicle's track.

    Attributes:
        status: started (no token), tracking, reset (token not trusted: ``reason``) or
            out_of_order (the frame is older than the token: the filter was not run).
        reason: why a reset happened (:data:`RESET_REASONS`), else None.
        estimate: the filter's estimate after the frame (None when out of order).
        steps: frames the belief moved (1: the next frame, more: frames dropped, 0: the
            same instant); None when out of order.
        track: the track to hand back (out of order: the previous one, unchanged).
    """

    status: Status
    reason: ResetReason | None
    estimate: Estimate | None
    steps: int | None
    track: Track


def follow(
    filt: SequenceFilter,
    binding: bytes,
    prev: Track | None,
    evidence: Evidence,
    *,
    vehicle: bytes,
    timestamp: float | None,
    now: float,
    max_age_s: float,
    dropped: int = 0,
    accept: Callable[[Estimate], bool] | None = None,
) -> Step:
    """One frame of a vehicle: check its previous track, move and weigh the belief.

    Args:
        filt, binding: the index version's filter and :func:`binding_digest`.
        prev: the track from the vehicle's previous answer (checked by
            :meth:`TokenCodec.decode`), or None to start.
        evidence: the frame's evidence (:data:`NO_EVIDENCE` when it has none).
        vehicle: :func:`vehicle_digest` of the vehicle.
        timestamp: the frame's capture time in seconds, if given.
        now: the server's time (epoch seconds), stamped into the new track.
        max_age_s: a track issued longer ago than this restarts (``expired``).
        dropped: frames known to be lost since ``prev`` (failed images of a batch).
        accept: whether the caller holds the new estimate (its acceptance, e.g. with
            hysteresis on :attr:`~hmpf.sequence.Estimate.held` and ``continuous``, or a
            lock kept through a frame: :attr:`hmpf.acceptance.Decision.holds`); its
            decision is packed into the track (:meth:`~hmpf.sequence.SequenceFilter.hold`).
            None: the state's decision is left as it was (False from the start).
    """
    ts = float("nan") if timestamp is None else float(timestamp)
    status: Status = "started" if prev is None else "tracking"
    reason: ResetReason | None = None
    if prev is not None and not hmac.compare_digest(prev.binding, binding):
        status, reason = "reset", "index_changed"
    elif prev is not None and now - prev.issued_at > max_age_s:
        status, reason = "reset", "expired"
    if prev is not None and status == "tracking":
        if ts < prev.timestamp:  # False when either is NaN
            return Step("out_of_order", None, None, None, prev)
        try:
            state = filt.unpack(prev.state)
        except StateError as exc:  # signed by us for this binding: cannot happen but by a bug
            raise TrackRefused("malformed", f"track: {exc}") from None
        steps, interval = frame_steps(ts - prev.timestamp, prev.interval)
        steps += dropped
    else:
        state, steps, interval = filt.start(), 1, float("nan")
    state, est = filt.update(state, evidence, steps)
    if accept is not None:
        state = filt.hold(state, bool(accept(est)))
    track = Track(binding, vehicle, now, ts, interval, filt.pack(state, KEEP))
    return Step(status, reason, est, steps, track)
