"""The experience log: frames the service localised with high confidence, kept on disk until
the indexer merges them into the map as new experiences of their places.

The service appends (:class:`ExperienceLog`, one writer per log); the indexer and the
``hmpf-experiences`` command read (:func:`read_log`) and delete (:func:`prune`). A log is a
folder::

    LOG/log.json        the log's identity, written once: {"format": "hmpf-experience-log",
                        "version": 1, "id": <uuid4 hex>, "created": <epoch s>}
    LOG/00000001.seg    append-only segments, oldest first (numbers only grow)
    LOG/.lock           flock held while the writer rotates or deletes, and by prune
    LOG/.writer         flock held by the live writer for its whole life

A segment is a run of frames, each self-checking, so that a write cut short (a kill -9, a
full disk, a power cut before the fsync) is recognised instead of being read as data::

    magic          4 bytes, b"HXR1"
    header length  u32, little-endian
    payload length u32, little-endian
    CRC-32         u32, over the two lengths, the header and the payload
    header         JSON (UTF-8): a record's fields but the image (and the features)
    payload        the image bytes as uploaded, then, when the header has
                   ``features_bytes``, that many bytes of the frame's features as the
                   service extracted them (:func:`hmpf.features.pack_features`), so that a
                   merge into the version that answered need not extract them again

A *torn* tail (the frame a writer was appending when it died) is skipped without an error;
a *damaged* stretch inside a segment (bytes changed on disk) is skipped by looking for the
next frame whose magic and CRC hold, and counted. Neither ever stops the frames after it
being read. A writer that starts on an existing log never writes into an old segment: it
opens a new one, so the bytes of every earlier record stay as they were written.

Privacy: the images are vehicles' camera frames, so the folder is created ``0700`` and the
segments ``0600``; :func:`prune` deletes by vehicle or by age.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import re
import struct
import time
import uuid
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hmpf.errors import HmpfError

__all__ = [
    "DEFAULT_MAX_BYTES",
    "DEFAULT_SEGMENT_BYTES",
    "DEFAULT_SYNC_EVERY",
    "DEFAULT_SYNC_INTERVAL_S",
    "MAX_GAP_S",
    "MODES",
    "ExperienceLog",
    "ExperienceLogError",
    "LogStats",
    "PruneReport",
    "Record",
    "log_id",
    "prune",
    "read_log",
]

#: What a record's ``mode`` may be: the answer came from the sequence filter or from one frame;
#: ``lead``: a frame a vehicle sent just before a recorded sequence-mode frame, not itself
#: confident (a lock's lead-in: its ``place`` and ``p_correct`` are its own answer's, and a
#: merge places it from the recorded frames after it, :func:`indexer.experiences.place_leads`).
MODES = ("sequence", "single", "lead")
#: The longest time (seconds, by the records' timestamps) between two frames of one vehicle
#: that still belong to one stretch of its drive: the recorder's bound from a lead-in frame
#: to the frame it leads into, and the merge's between time neighbours (beyond it, the
#: vehicle may have gone anywhere in between).
MAX_GAP_S = 30.0
DEFAULT_MAX_BYTES = 1 << 30  # 1 GiB: about 6,000 frames of a 50 KB JPEG + 110 KB of features
DEFAULT_SEGMENT_BYTES = 64 << 20
DEFAULT_SYNC_EVERY = 32
DEFAULT_SYNC_INTERVAL_S = 1.0

HEADER_FILE = "log.json"
LOCK_FILE = ".lock"
WRITER_FILE = ".writer"
FORMAT = "hmpf-experience-log"
VERSION = 1

MAGIC = b"HXR1"
_PREFIX = struct.Struct("<4sIII")  # magic, header length, payload length, CRC-32
_LENGTHS = struct.Struct("<II")
#: Sanity bounds of a frame: larger lengths are damage, not a record (no allocation of them).
MAX_HEADER_BYTES = 64 << 10
MAX_PAYLOAD_BYTES = 256 << 20
_SEGMENT = re.compile(r"^(\d{8,})\.seg$")
_TMP_SUFFIX = ".tmp"
#: How long a new writer waits for ``.writer`` (prune takes it for an instant to test it).
_WRITER_WAIT_S = 0.5


class ExperienceLogError(HmpfError):
    """A folder that is not an experience log, one another writer holds, or a writer used
    after :meth:`ExperienceLog.close`."""


@dataclass(frozen=True)
class Record:
    """One recorded frame.

    Attributes:
        image: the uploaded frame, as received (JPEG/PNG/...).
        content_type: its declared content type (None: none was given).
        place: the matched place (reference index) in ``index_version``.
        place_name: the matched reference's name (what a merge maps by).
        index_version: the index version that answered, e.g. ``"v0003"``.
        p_correct: the answer's calibrated probability of being right.
        vehicle: the vehicle's id; ``""`` when the request named none.
        timestamp: when the frame was taken: the request's timestamp as sent, else when it
            was received (seconds since the epoch).
        mode: ``"sequence"`` or ``"single"`` (where the answer came from), or ``"lead"``
            (a lock's lead-in, :data:`MODES`).
        log: the log's id (stable, unique per log folder).
        seq: the record's number in the log (unique with ``log``; grows with time).
        received: when the service received the frame (seconds since the epoch): the clock
            retention by age goes by (a request's timestamp may use the vehicle's own epoch).
            NaN for a record written without one.
        features: the frame's features as the answering version's methods extracted them
            (:func:`hmpf.features.pack_features`, which names those methods); None when not
            recorded (records written before they were, or recording without them).
    """

    image: bytes
    content_type: str | None
    place: int
    place_name: str
    index_version: str
    p_correct: float
    vehicle: str
    timestamp: float
    mode: str
    log: str
    seq: int
    received: float = math.nan
    features: bytes | None = field(default=None, repr=False)

    def header(self) -> dict[str, Any]:
        """The record's fields but the image and features, as stored in its frame's header
        (with the features' length when there are some)."""
        head = {
            "seq": self.seq,
            "log": self.log,
            "place": self.place,
            "place_name": self.place_name,
            "index_version": self.index_version,
            "p_correct": self.p_correct,
            "vehicle": self.vehicle,
            "timestamp": self.timestamp,
            "received": None if math.isnan(self.received) else self.received,
            "mode": self.mode,
            "content_type": self.content_type,
        }
        if self.features is not None:
            head["features_bytes"] = len(self.features)
        return head

    def payload(self) -> bytes:
        """The frame's payload: the image, then the features (when there are some)."""
        return self.image if self.features is None else self.image + self.features

    @property
    def age_time(self) -> float:
        """The time retention by age compares: ``received``, else ``timestamp``."""
        return self.timestamp if math.isnan(self.received) else self.received


@dataclass
class LogStats:
    """What reading a log met besides its records (filled in as :func:`read_log` goes).

    Attributes:
        segments: segment files read.
        records: intact records read.
        damaged: damaged stretches skipped inside segments (each one or more lost records).
        torn: segments that end in a frame cut short (a writer stopped while appending).
        skipped_bytes: bytes of both kinds, skipped.
        bytes: the segments' size.
    """

    segments: int = 0
    records: int = 0
    damaged: int = 0
    torn: int = 0
    skipped_bytes: int = 0
    bytes: int = 0


# -- frames -----------------------------------------------------------------------------------
def encode_frame(header: dict[str, Any], payload: bytes) -> bytes:
    """One frame: the prefix, ``header`` as JSON and ``payload``.

    Raises:
        ValueError: a header or payload over the bounds a reader accepts.
    """
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    if len(head) > MAX_HEADER_BYTES or len(payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(
            f"a record holds at most {MAX_PAYLOAD_BYTES} image bytes and {MAX_HEADER_BYTES} "
            f"header bytes (got {len(payload)} and {len(head)})"
        )
    lengths = _LENGTHS.pack(len(head), len(payload))
    crc = zlib.crc32(payload, zlib.crc32(head, zlib.crc32(lengths)))
    return _PREFIX.pack(MAGIC, len(head), len(payload), crc) + head + payload


@dataclass(frozen=True)
class _Frame:
    header: dict[str, Any]
    payload: bytes
    start: int
    end: int

    @property
    def seq(self) -> int:
        return int(self.header["seq"])

    @property
    def is_mark(self) -> bool:
        """A mark (written by prune) keeps a removed record's ``seq`` as the log's latest."""
        return bool(self.header.get("mark"))


def _frame_at(data: bytes, pos: int) -> _Frame | None:
    """The intact frame starting at ``pos``, or None (not a frame, cut short, or damaged)."""
    if pos + _PREFIX.size > len(data):
        return None
    magic, hlen, plen, crc = _PREFIX.unpack_from(data, pos)
    if magic != MAGIC or not 0 < hlen <= MAX_HEADER_BYTES or plen > MAX_PAYLOAD_BYTES:
        return None
    body = pos + _PREFIX.size
    end = body + hlen + plen
    if end > len(data):
        return None
    view = memoryview(data)
    head, payload = view[body : body + hlen], view[body + hlen : end]
    if zlib.crc32(payload, zlib.crc32(head, zlib.crc32(_LENGTHS.pack(hlen, plen)))) != crc:
        return None
    try:
        header = json.loads(bytes(head))
    except ValueError:
        return None
    if not isinstance(header, dict) or not isinstance(header.get("seq"), int):
        return None
    return _Frame(header, bytes(payload), pos, end)


def _next_frame(data: bytes, start: int) -> _Frame | None:
    """The first intact frame at or after ``start`` (found by its magic, checked by its CRC)."""
    i = data.find(MAGIC, start)
    while i != -1:
        frame = _frame_at(data, i)
        if frame is not None:
            return frame
        i = data.find(MAGIC, i + 1)
    return None


def _scan(data: bytes, stats: LogStats) -> Iterator[_Frame]:
    """Every intact frame of one segment's bytes, in order; damage and a torn tail counted."""
    pos = 0
    while pos < len(data):
        frame = _frame_at(data, pos)
        if frame is None:
            frame = _next_frame(data, pos + 1)
            if frame is None:  # nothing intact after it: the frame a writer was cut off in
                stats.torn += 1
                stats.skipped_bytes += len(data) - pos
                return
            stats.damaged += 1
            stats.skipped_bytes += frame.start - pos
        yield frame
        pos = frame.end


def _record(frame: _Frame) -> Record | None:
    """The frame's record; None for a mark or a header that does not hold one."""
    if frame.is_mark:
        return None
    h = frame.header
    try:
        received = h.get("received")
        n_features = h.get("features_bytes")
        image, features = frame.payload, None
        if n_features is not None:
            if not 0 < _int(n_features) <= len(image):
                raise ValueError("features_bytes out of range")
            image, features = image[:-n_features], image[-n_features:]
        rec = Record(
            image=image,
            content_type=_opt_str(h.get("content_type")),
            place=_int(h["place"]),
            place_name=_str(h["place_name"]),
            index_version=_str(h["index_version"]),
            p_correct=float(h["p_correct"]),
            vehicle=_str(h["vehicle"]),
            timestamp=float(h["timestamp"]),
            mode=_str(h["mode"]),
            log=_str(h["log"]),
            seq=_int(h["seq"]),
            received=math.nan if received is None else float(received),
            features=features,
        )
    except (KeyError, TypeError, ValueError):
        return None
    return rec


def _int(x: Any) -> int:
    if not isinstance(x, int) or isinstance(x, bool):
        raise TypeError("not an integer")
    return x


def _str(x: Any) -> str:
    if not isinstance(x, str):
        raise TypeError("not a string")
    return x


def _opt_str(x: Any) -> str | None:
    return None if x is None else _str(x)


# -- the folder ---------------------------------------------------------------------------------
def _segments(folder: Path) -> list[Path]:
    """The segment files, oldest first."""
    try:
        names = os.listdir(folder)
    except FileNotFoundError:
        return []
    found = [(int(m.group(1)), n) for n in names if (m := _SEGMENT.match(n))]
    return [folder / n for _, n in sorted(found)]


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:  # deleted (bound, prune) after it was listed
        return b""


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """Hold the log's ``.lock`` (rotation, deletion, prune: one at a time)."""
    fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def _writer_live(folder: Path) -> bool:
    """Whether a writer holds the log (its ``.writer`` lock), tested without waiting."""
    fd = os.open(folder / WRITER_FILE, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


def _read_header(folder: Path) -> dict[str, Any]:
    path = folder / HEADER_FILE
    if not folder.is_dir():
        raise ExperienceLogError(f"{folder}: no such experience log (not a folder)")
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ExperienceLogError(f"{folder}: not an experience log (no {HEADER_FILE})") from None
    except (OSError, ValueError) as exc:
        raise ExperienceLogError(f"{path}: cannot be read: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ExperienceLogError(f"{path}: not an experience log header")
    if data.get("version") != VERSION or not isinstance(data.get("id"), str):
        raise ExperienceLogError(
            f"{path}: experience log version {data.get('version')!r} is not supported "
            f"(this hmpf reads version {VERSION})"
        )
    return data


def _create_header(folder: Path) -> None:
    """Write ``log.json`` (atomically) in a folder that holds nothing else of substance."""
    ours = {LOCK_FILE, WRITER_FILE}
    others = [n for n in os.listdir(folder) if n not in ours and not n.endswith(_TMP_SUFFIX)]
    if others:
        raise ExperienceLogError(
            f"{folder}: not an experience log (no {HEADER_FILE}) and not empty: "
            "name an empty or new folder"
        )
    header = {"format": FORMAT, "version": VERSION, "id": uuid.uuid4().hex, "created": time.time()}
    _write_atomic(folder / HEADER_FILE, json.dumps(header, indent=1).encode() + b"\n")


def _write_atomic(path: Path, data: bytes) -> None:
    """``data`` as ``path``: written beside it, fsynced, renamed over it, the folder fsynced."""
    tmp = path.with_name(path.name + _TMP_SUFFIX)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _remove_stale_tmp(folder: Path) -> None:
    """Files a killed prune left half-written (the originals are intact)."""
    for name in os.listdir(folder):
        if name.endswith(_TMP_SUFFIX):
            (folder / name).unlink(missing_ok=True)


def _latest_seq(segments: list[Path]) -> int:
    """The largest ``seq`` in the log (records and marks), -1 when there is none: the newest
    segment holding a frame has it (seq grows from segment to segment)."""
    for seg in reversed(segments):
        seqs = [f.seq for f in _scan(_read_bytes(seg), LogStats())]
        if seqs:
            return max(seqs)
    return -1


def log_id(path: str | Path) -> str:
    """The id of the log at ``path``.

    Raises:
        ExperienceLogError: ``path`` is not an experience log.
    """
    return str(_read_header(Path(path))["id"])


# -- reading ------------------------------------------------------------------------------------
def read_log(path: str | Path, *, stats: LogStats | None = None) -> Iterator[Record]:
    """Every intact record of the log at ``path``, oldest first.

    A torn tail (a frame cut short) and damaged stretches are skipped, never raised;
    ``stats`` (when given) counts them as the iteration goes. Safe while a writer appends
    (its torn tail is the frame being written) and while :func:`prune` runs (each segment is
    read whole, before or after prune replaced it). Needs no lock.

    Raises:
        ExperienceLogError: ``path`` is not an experience log (at the call, not the first
            iteration).
    """
    folder = Path(path)
    _read_header(folder)
    return _records(folder, stats if stats is not None else LogStats())


def _records(folder: Path, stats: LogStats) -> Iterator[Record]:
    for seg in _segments(folder):
        data = _read_bytes(seg)
        stats.segments += 1
        stats.bytes += len(data)
        for frame in _scan(data, stats):
            rec = _record(frame)
            if rec is None and not frame.is_mark:
                stats.damaged += 1  # intact bytes, but not a record this version reads
            if rec is not None:
                stats.records += 1
                yield rec


# -- writing ------------------------------------------------------------------------------------
class ExperienceLog:
    """The writer of one log: append-only, fsynced in batches, bounded in size.

    One writer per log (a second one is refused: :class:`ExperienceLogError`). Records are
    written whole (one ``write``, more only after a partial one) straight into the current
    segment, with no buffer in the process, so a kill -9 of the process loses at most the
    record being written (a torn tail); :meth:`flush` (every ``sync_every`` records or
    ``sync_interval_s`` seconds, whichever first, and on rotation and close) fsyncs, so a
    power cut loses at most the records appended since. Not thread-safe: one thread appends.

    A writer never writes into a segment it did not create: it starts a new one (when its
    first record comes), then a new one whenever the next record would take the current past
    ``segment_bytes``. When the segments together pass ``max_bytes``, the oldest ones are
    deleted (never the current one), their records counted in :attr:`dropped`.

    Args:
        path: the log's folder, created (``0700``, with ``log.json``) when missing or empty.
        max_bytes: the bound on the segments' total size.
        segment_bytes: the size a segment is closed at (at most ``max_bytes / 2``, so that the
            bound deletes in steps).
        sync_every: records between fsyncs at most.
        sync_interval_s: seconds an appended record waits for its fsync at most (checked at
            each append and at :meth:`maybe_flush`; a caller with no records to append calls
            that now and then).

    Raises:
        ExperienceLogError: ``path`` is a folder with other files, another writer holds it,
            or a bound is invalid.
        OSError: the folder cannot be created or written.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
        segment_bytes: int = DEFAULT_SEGMENT_BYTES,
        sync_every: int = DEFAULT_SYNC_EVERY,
        sync_interval_s: float = DEFAULT_SYNC_INTERVAL_S,
    ) -> None:
        if segment_bytes < 1 or max_bytes < 2 * segment_bytes:
            raise ExperienceLogError(
                f"segment_bytes ({segment_bytes}) must be >= 1 and at most half of max_bytes "
                f"({max_bytes})"
            )
        if sync_every < 1 or not sync_interval_s > 0:
            raise ExperienceLogError("sync_every must be >= 1 and sync_interval_s > 0")
        self.path = Path(path)
        self.max_bytes, self.segment_bytes = max_bytes, segment_bytes
        self.sync_every, self.sync_interval_s = sync_every, sync_interval_s
        self.path.mkdir(mode=0o700, parents=True, exist_ok=True)
        self._writer_fd: int | None = _take_writer(self.path)
        try:
            with _locked(self.path):
                if not (self.path / HEADER_FILE).exists():
                    _create_header(self.path)
                self.id = str(_read_header(self.path)["id"])
                _remove_stale_tmp(self.path)
                segments = _segments(self.path)
                self._next_seq = _latest_seq(segments) + 1
                self._bytes = sum(_size(s) for s in segments)
        except BaseException:
            self._release()
            raise
        self._fd: int | None = None
        self._segment: Path | None = None
        self._size = 0  # of the current segment
        self._unsynced = 0
        self._since = 0.0  # monotonic time of the oldest unsynced record
        #: Records appended by this writer.
        self.appended = 0
        #: Records deleted by the size bound since this writer opened.
        self.dropped = 0

    @property
    def total_bytes(self) -> int:
        """The segments' total size, as of the last append (prune may have shrunk it since)."""
        return self._bytes

    @property
    def next_seq(self) -> int:
        return self._next_seq

    @property
    def closed(self) -> bool:
        return self._writer_fd is None

    def append(
        self,
        image: bytes,
        *,
        content_type: str | None,
        place: int,
        place_name: str,
        index_version: str,
        p_correct: float,
        vehicle: str,
        timestamp: float,
        mode: str,
        received: float | None = None,
        features: bytes | None = None,
    ) -> Record:
        """Append one frame (``features``: its packed features, or None); its
        :class:`Record` (with ``log`` and ``seq``) back.

        Raises:
            ValueError: a field out of range (a negative place, p_correct outside [0, 1], a
                mode not in :data:`MODES`, a time that is not finite, an image over 256 MiB).
            OSError: the write failed (e.g. a full disk); the segment is left as it was
                before it (or, when even that fails, closed: the next record opens a new one).
            ExperienceLogError: the writer is closed.
        """
        if self.closed:
            raise ExperienceLogError(f"{self.path}: the writer is closed")
        rec = Record(
            image=bytes(image),
            content_type=content_type,
            place=place,
            place_name=place_name,
            index_version=index_version,
            p_correct=float(p_correct),
            vehicle=vehicle,
            timestamp=float(timestamp),
            mode=mode,
            log=self.id,
            seq=self._next_seq,
            received=time.time() if received is None else float(received),
            features=None if features is None else bytes(features),
        )
        _check(rec)
        frame = encode_frame(rec.header(), rec.payload())
        if self._fd is None or (self._size > 0 and self._size + len(frame) > self.segment_bytes):
            self._rotate()
        self._write(frame)
        self._next_seq += 1
        self._size += len(frame)
        self._bytes += len(frame)
        self.appended += 1
        if self._unsynced == 0:
            self._since = time.monotonic()
        self._unsynced += 1
        if self._bytes > self.max_bytes:
            self._enforce_bound()
        if self._unsynced >= self.sync_every:
            self.flush()
        else:
            self.maybe_flush()
        return rec

    def flush(self) -> None:
        """fsync the records appended so far."""
        if self._fd is not None and self._unsynced:
            os.fsync(self._fd)
        self._unsynced = 0

    def maybe_flush(self) -> bool:
        """fsync when the oldest unsynced record has waited ``sync_interval_s``; whether it did."""
        if self._unsynced and time.monotonic() - self._since >= self.sync_interval_s:
            self.flush()
            return True
        return False

    def close(self) -> None:
        """Flush, close the segment and release the log (idempotent)."""
        try:
            if self._fd is not None:
                try:
                    self.flush()
                finally:
                    os.close(self._fd)
                    self._fd = None
        finally:
            self._release()

    def __enter__(self) -> ExperienceLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _release(self) -> None:
        if self._writer_fd is not None:
            os.close(self._writer_fd)
            self._writer_fd = None

    def _write(self, frame: bytes) -> None:
        assert self._fd is not None
        view = memoryview(frame)
        try:
            while view:
                view = view[os.write(self._fd, view) :]
        except OSError:
            # Take back what part of the frame got out, so the next record follows the last
            # intact one; if even that fails, leave the torn frame as the segment's end.
            try:
                os.ftruncate(self._fd, self._size)
            except OSError:
                os.close(self._fd)
                self._fd = None
            raise

    def _rotate(self) -> None:
        """Close the current segment (fsynced) and start the next one."""
        with _locked(self.path):
            if self._fd is not None:
                fd, self._fd = self._fd, None
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
                self._unsynced = 0
            segments = _segments(self.path)
            number = int(segments[-1].name.split(".")[0]) + 1 if segments else 1
            seg = self.path / f"{number:08d}.seg"
            self._fd = os.open(seg, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o600)
            self._segment, self._size = seg, 0
            _fsync_dir(self.path)
            self._bytes = sum(_size(s) for s in segments)

    def _enforce_bound(self) -> None:
        """Delete the oldest segments while the log is over ``max_bytes`` (never the current)."""
        with _locked(self.path):
            segments = [(s, _size(s)) for s in _segments(self.path)]
            total = sum(n for _, n in segments)
            deleted = False
            for seg, n in segments:
                if total <= self.max_bytes or seg == self._segment:
                    break
                stats = LogStats()
                self.dropped += sum(1 for f in _scan(_read_bytes(seg), stats) if not f.is_mark)
                seg.unlink(missing_ok=True)
                total -= n
                deleted = True
            if deleted:
                _fsync_dir(self.path)
            self._bytes = total


def _take_writer(folder: Path) -> int:
    """Hold ``.writer`` (waiting briefly: prune tests it for an instant)."""
    fd = os.open(folder / WRITER_FILE, os.O_RDWR | os.O_CREAT, 0o600)
    deadline = time.monotonic() + _WRITER_WAIT_S
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
        except BlockingIOError:
            if time.monotonic() >= deadline:
                os.close(fd)
                raise ExperienceLogError(
                    f"{folder}: another process is writing this experience log (one writer "
                    "per log: give each service its own folder)"
                ) from None
            time.sleep(0.05)


def _check(rec: Record) -> None:
    if rec.place < 0:
        raise ValueError(f"place must be >= 0 (got {rec.place})")
    if not 0.0 <= rec.p_correct <= 1.0:
        raise ValueError(f"p_correct must be in [0, 1] (got {rec.p_correct})")
    if rec.mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)} (got {rec.mode!r})")
    if not (math.isfinite(rec.timestamp) and math.isfinite(rec.received)):
        raise ValueError("timestamp and received must be finite")
    if rec.features is not None and not rec.features:
        raise ValueError("features, when given, must not be empty")


# -- retention ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class PruneReport:
    """What :func:`prune` did (or, with ``dry_run``, would do).

    Attributes:
        removed: matching records removed.
        kept: records kept.
        pending: matching records left in the segment a live writer is appending to (removed
            by a later prune, once the writer has moved on to a new segment or stopped).
        rewritten: segments rewritten without their matching records.
        deleted: segments deleted (nothing was left in them).
        dry_run: nothing was changed.
        stats: what reading the segments met (records, torn tails, damaged stretches).
    """

    removed: int
    kept: int
    pending: int
    rewritten: int
    deleted: int
    dry_run: bool
    stats: LogStats = field(default_factory=LogStats)


def prune(
    path: str | Path,
    *,
    vehicle: str | None = None,
    older_than_s: float | None = None,
    now: float | None = None,
    dry_run: bool = False,
) -> PruneReport:
    """Delete the records of ``vehicle`` and those older than ``older_than_s``.

    A record is older than ``older_than_s`` when it was received (:attr:`Record.age_time`)
    more than that many seconds before ``now`` (default: the current time). Each segment
    with a matching record is rewritten without it (a new file beside it, fsynced, renamed
    over it, the folder fsynced), or deleted when nothing is left in it; damaged and torn
    bytes in a rewritten segment go too (they were unreadable). A kill at any point leaves
    every segment either as it was or rewritten, never half of each.

    Safe with a live writer, in another process or this one: prune holds the log's
    ``.lock`` throughout, so the writer can neither rotate nor delete for its bound while
    prune runs (it waits; the service's recorder drops frames meanwhile rather than waiting
    in a request), and prune never touches the segment a live writer is appending to (the
    newest one while a writer holds ``.writer``): matching records there are left and
    counted as :attr:`PruneReport.pending`. Without a live writer every segment is pruned.
    Readers (:func:`read_log`) need no lock: they see each segment before or after.

    Raises:
        ValueError: neither ``vehicle`` nor ``older_than_s`` given, or a negative age.
        ExperienceLogError: ``path`` is not an experience log.
    """
    if vehicle is None and older_than_s is None:
        raise ValueError("say what to prune: a vehicle, an age, or both")
    if older_than_s is not None and not older_than_s >= 0:
        raise ValueError(f"older_than_s must be >= 0 (got {older_than_s})")
    folder = Path(path)
    log = str(_read_header(folder)["id"])
    cutoff = None if older_than_s is None else (time.time() if now is None else now) - older_than_s

    def matches(rec: Record) -> bool:
        if vehicle is not None and rec.vehicle == vehicle:
            return True
        return cutoff is not None and rec.age_time < cutoff

    stats = LogStats()
    removed = kept = pending = rewritten = deleted = 0
    with _locked(folder):
        if not dry_run:
            _remove_stale_tmp(folder)
        live = _writer_live(folder)
        segments = _segments(folder)
        anchor = _anchor(segments)
        for i, seg in enumerate(segments):
            data = _read_bytes(seg)
            stats.segments += 1
            stats.bytes += len(data)
            frames = list(_scan(data, stats))
            records = [(f, _record(f)) for f in frames]
            hit = {f.start for f, r in records if r is not None and matches(r)}
            n_records = sum(1 for _, r in records if r is not None)
            stats.records += n_records
            kept += n_records - len(hit)
            if live and i == len(segments) - 1:
                pending += len(hit)
                continue
            removed += len(hit)
            if not hit or dry_run:
                continue
            keep = [f for f in frames if f.start not in hit]
            if i < anchor and all(f.is_mark for f in keep):
                seg.unlink()
                deleted += 1
                continue
            out = b"".join(data[f.start : f.end] for f in keep)  # the bytes as written
            latest = max(f.seq for f in frames)
            if not keep or max(f.seq for f in keep) < latest:
                out += encode_frame({"seq": latest, "log": log, "mark": True}, b"")
            _write_atomic(seg, out)
            rewritten += 1
        if deleted:
            _fsync_dir(folder)
    return PruneReport(removed, kept, pending, rewritten, deleted, dry_run, stats)


def _anchor(segments: list[Path]) -> int:
    """The position of the newest segment holding a frame (-1: none). It keeps the log's
    latest seq, which a new writer goes on from: prune rewrites it (with a mark when its
    last frame goes) but never deletes it."""
    for i in range(len(segments) - 1, -1, -1):
        if next(_scan(_read_bytes(segments[i]), LogStats()), None) is not None:
            return i
    return -1
