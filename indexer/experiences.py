"""Fleet experiences: frames the service recorded, merged offline into a new index version,
and removed again by where they came from.

    hmpf-index add --index maps/campus --experiences LOG [LOG ...] [--dry-run]
    hmpf-index remove --index maps/campus --experiences-from vehicle=V|log=L|before=TIME

A merge (:func:`merge`) is a version like any other (:class:`indexer.build.VersionTransaction`:
writer lock, work folder, manifest, verification, atomic publish, ``--resume``). Each frame
passes, in order, through these gates; the first it fails is counted (``MergeReport.gates``):

* ``already_merged``: the same frame of the same log is in the version, or the input repeats a
  record (merging a log twice adds nothing);
* ``below_p_correct``: its recorded ``p_correct`` is below ``min_p_correct`` (not asked of a
  ``lead`` frame: the frames after it vouch for it, next);
* ``unknown_place``: the place it was recorded at (by name) is not a place of the version;
* ``unreadable``: the bytes do not decode;
* ``unplaced``: a ``lead`` frame (a lock's lead-in, recorded before a frame of the same
  vehicle) that :func:`place_leads` cannot place: no two frames of its vehicle kept by the
  gates above follow it closely enough to give the vehicle's pace, its place would lie
  before the route's start (or past its end), or its own answer is more than a place from
  there; every lead frame with ``place_leads`` off;
* ``disagreeing``: localised on its own against the version (one frame, the whole hierarchy,
  over places) it lands more than ``agreement_window`` places from its recorded place along
  that place's route: the defence against wrong frames (a poisoned log, a wrong lock);
* ``duplicate``: its tier-1 descriptor (the first global method of tier 1) has a cosine
  similarity of at least ``duplicate_similarity`` to an image its place holds already or to a
  frame of the same place kept before it in this merge;
* ``over_cap``: its place would hold more than ``max_per_place`` images (the original
  reference included); the frames kept are chosen greedily, each the farthest (on that
  descriptor) from the images the place holds and those chosen before it.

Before the gates that need features, a lead frame is placed from the frames after it
(``place_leads``, :func:`place_leads`): by the pace of its vehicle over the next frames kept,
back from the first of them; and a frame may be moved one place
(``interpolate_places``, :func:`between_neighbours`): where the frames just before and after
it from the same log and vehicle, equally spaced in time, advanced an even number of places
along one route, and its recorded place is one place off the place midway between them, it
is placed there. A recorder's answers jitter by a place (two consecutive frames answered at
one place, the next place left without an experience); the vehicle's pace between its
neighbours says where it was (``MergeReport.interpolated`` counts the frames moved).

The knobs come from the hierarchy config's ``experiences:`` section
(:class:`hmpf.config.ExperienceSettings`), command-line flags over them; a merge records the
values it used, the logs and the counts in the manifest (``experiences``). A frame's features
are read from its record when the service recorded them (setting ``experience_features``)
with methods equal to the version's (the same :meth:`~hmpf.methods.base.Method.descriptor_key`:
parameters, fitted state, CNN runtime; :func:`hmpf.features.unpack_features`): those are the
features the service answered the frame with. The others are extracted once each, by the
build's own extraction (Ray included). Every frame is written to the work folder as a file
first. Experience rows follow the places (the format's order,
:data:`hmpf.index.tables.EXPERIENCE_COLUMNS`), named ``exp-<log>-<record>`` with the image's
extension, with the frame's sha256, no source folder, a thumbnail and their provenance.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import tempfile
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from pydantic import ValidationError

from hmpf.config import ExperienceSettings
from hmpf.errors import DatasetError
from hmpf.experience_log import MAX_GAP_S, read_log
from hmpf.features import unpack_features
from hmpf.hierarchy import Hierarchy
from hmpf.imageio import probe_image
from hmpf.index.layout import IndexBuildError
from hmpf.index.reader import IndexReader
from hmpf.index.tables import (
    Ragged,
    RefTable,
    columns_from_features,
    concat_columns,
    select_columns,
)
from hmpf.methods import Method
from hmpf.methods.registry import format_validation_error
from hmpf.sequence import RouteMap
from indexer.build import (
    BuildOptions,
    NewVersion,
    Summary,
    VersionTransaction,
    WorkDir,
    _extract,
    _parent,
    _parent_options,
    _row_thumbnails,
    _thumbnails,
    experience_lines,
    place_count,
    without_empty_experiences,
)

__all__ = [
    "GATES",
    "between_neighbours",
    "place_leads",
    "FrameRecord",
    "LogRecords",
    "MergeReport",
    "merge",
    "parse_filters",
    "remove_experiences",
]

#: The gates, in the order a frame meets them (see the module docstring).
GATES = (
    "already_merged",
    "below_p_correct",
    "unknown_place",
    "unreadable",
    "unplaced",
    "disagreeing",
    "duplicate",
    "over_cap",
)
#: Frames named in the report as rejected by the agreement gate (the rest are counted).
MAX_LISTED = 20
#: The longest time (seconds) between a frame and each of its neighbours for
#: :func:`between_neighbours` to place it by them, and between a lead frame and the frames
#: after it for :func:`place_leads` (the log's own bound, shared with the recorder).
MAX_NEIGHBOUR_GAP_S = MAX_GAP_S
#: How unequal the two time steps to a frame's neighbours may be, as a share of the longer
#: (:func:`between_neighbours`): a constant pace needs about equal steps.
NEIGHBOUR_STEP_TOLERANCE = 0.25
#: How many of the frames kept after a lead frame give its vehicle's pace
#: (:func:`place_leads`): the first and the last of them, over the time between.
LEAD_PACE_FRAMES = 5
#: How far (places along the route) a lead frame's own answer may be from where the frames
#: after it place it (:func:`place_leads`): two estimates of one place must agree.
LEAD_AGREEMENT = 1
_EXTENSIONS = {
    "image/jpeg": ".jpg",
    "image/png": ".png",
    "image/webp": ".webp",
    "image/bmp": ".bmp",
    "image/tiff": ".tif",
}


class FrameRecord(Protocol):
    """What a merge reads of one recorded frame (:class:`hmpf.experience_log.Record`)."""

    @property
    def image(self) -> bytes: ...
    @property
    def content_type(self) -> str | None: ...
    @property
    def place_name(self) -> str: ...
    @property
    def index_version(self) -> str: ...
    @property
    def p_correct(self) -> float: ...
    @property
    def vehicle(self) -> str: ...
    @property
    def timestamp(self) -> float: ...
    @property
    def log(self) -> str: ...
    @property
    def seq(self) -> int: ...
    @property
    def features(self) -> bytes | None: ...
    @property
    def mode(self) -> str: ...


@dataclass(frozen=True)
class _Candidate:
    """A record that passed the gates needing no features (metadata only: no bytes)."""

    log: str
    seq: int
    sha256: str
    place: int
    name: str
    p_correct: float
    vehicle: str
    version: str
    time: float
    lead: bool = False


@dataclass
class MergeReport:
    """What a merge did, or, in a dry run, would do.

    Attributes:
        version: the published version; None in a dry run or when nothing was added.
        records: frames read from the logs.
        gates: gate -> frames it stopped (:data:`GATES`, in order).
        added: experiences added (per place: ``added_per_place``).
        frames_extracted: frames whose features were extracted (those reaching the gates that
            need features, but for ``features_recorded``).
        features_recorded: frames reaching those gates whose features came from the log (the
            service recorded them with the frame, extracted by the same methods).
        interpolated: frames placed between their time neighbours, one place from where
            they were recorded (:func:`between_neighbours`).
        leads_placed: lead frames placed from the frames after them (:func:`place_leads`;
            the ones it could not place are the ``unplaced`` gate's).
        seconds: from the start to the end of the gates (publishing excluded).
        rejected_agreement: the first frames the agreement gate stopped, one line each.
        summary: the published version's :class:`~indexer.build.Summary` (None: nothing
            published).
    """

    logs: list[str]
    records: int
    gates: dict[str, int]
    added: int
    frames_extracted: int
    seconds: float
    settings: dict[str, Any]
    dry_run: bool = False
    version: str | None = None
    parent: str = ""
    added_per_place: dict[int, int] = field(default_factory=dict)
    rejected_agreement: list[str] = field(default_factory=list)
    places: dict[str, int] = field(default_factory=dict)
    summary: Summary | None = None
    features_recorded: int = 0
    interpolated: int = 0
    leads_placed: int = 0

    @property
    def frames_per_s(self) -> float:
        """Frames through the gates that need features, per second."""
        return (self.frames_extracted + self.features_recorded) / max(self.seconds, 1e-9)

    def to_json(self) -> dict[str, Any]:
        """The manifest's ``experiences`` entry."""
        return {
            "operation": "merge",
            "logs": list(self.logs),
            "records": self.records,
            "gates": dict(self.gates),
            "added": self.added,
            "added_per_place": {str(k): v for k, v in sorted(self.added_per_place.items())},
            "frames_extracted": self.frames_extracted,
            "features_recorded": self.features_recorded,
            "interpolated": self.interpolated,
            "leads_placed": self.leads_placed,
            "frames_per_s": round(self.frames_per_s, 2),
            "seconds": round(self.seconds, 3),
            "settings": dict(self.settings),
            "rejected_agreement": list(self.rejected_agreement),
            "places": dict(self.places),
        }

    def lines(self) -> list[str]:
        """For the terminal: the summary of a published merge, else what it would add."""
        if self.summary is not None:
            return self.summary.lines()
        head = (
            f"dry run: nothing written; merging into {self.parent} would add {self.added} "
            "experience(s)"
            if self.dry_run
            else f"nothing to add: no new version (current {self.parent})"
        )
        return [head, *experience_lines(self.to_json())]


# -- inputs ----------------------------------------------------------------------------------
class LogRecords:
    """The records of experience logs (:func:`hmpf.experience_log.read_log`), in the order
    given, readable more than once (a merge reads its input twice).

    Raises:
        DatasetError: a path that does not exist (ExperienceLogError, when reading, for one
            that is not a log).
    """

    def __init__(self, paths: Sequence[str | Path]) -> None:
        self.paths = [Path(p) for p in paths]
        for p in self.paths:
            if not p.exists():
                raise DatasetError(f"experience log {str(p)!r}: no such file or folder")

    def __iter__(self) -> Iterator[FrameRecord]:
        for p in self.paths:
            yield from read_log(p)


def resolve_settings(
    base: ExperienceSettings, overrides: Mapping[str, Any] | None, gates: bool = True
) -> ExperienceSettings:
    """``base`` with the given (not None) ``overrides``, validated as the config is; without
    ``gates``, every gate open (:meth:`~hmpf.config.ExperienceSettings.open`, overrides
    ignored but ``interpolate_places`` and ``place_leads``, which are not gates).

    ``agreement_window`` may be overridden with a negative number to turn the gate off.

    Raises:
        DatasetError: an override out of range.
    """
    if not gates:
        given = overrides or {}
        kept = {}
        for key in ("interpolate_places", "place_leads"):
            value = given.get(key)
            kept[key] = getattr(base, key) if value is None else bool(value)
        return ExperienceSettings.open().model_copy(update=kept)
    data = base.model_dump()
    for key, value in (overrides or {}).items():
        if value is None:
            continue
        if key == "agreement_window" and value < 0:
            value = None
        data[key] = value
    try:
        return ExperienceSettings.model_validate(data)
    except ValidationError as exc:
        raise DatasetError(format_validation_error(exc, "experience merge settings")) from None


def _extension(data: bytes, content_type: str | None) -> str:
    """The file extension of an image by its first bytes, else by its content type."""
    if data.startswith(b"\xff\xd8"):
        return ".jpg"
    if data.startswith(b"\x89PNG"):
        return ".png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return ".webp"
    if data.startswith(b"BM"):
        return ".bmp"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return ".tif"
    return _EXTENSIONS.get((content_type or "").split(";")[0].strip().lower(), ".jpg")


def _tag(log: str) -> str:
    """The log id's first characters that are safe in a file name."""
    return re.sub(r"[^A-Za-z0-9_-]", "", log)[:12] or "log"


def _repeatable(records: Iterable[FrameRecord]) -> Iterable[FrameRecord]:
    """``records`` as something that can be read twice (a merge reads its input twice: once
    for what the job is, once to write the chosen frames; only metadata is kept between)."""
    return list(records) if iter(records) is records else records


def _screen(
    parent: IndexReader, records: Iterable[FrameRecord], settings: ExperienceSettings
) -> tuple[list[_Candidate], dict[str, int], int, list[str], str]:
    """First pass: the gates needing no features, the rows' names, and the job's identity.

    Returns:
        (candidates in record order, gate counts, records read, log ids in order of first
        appearance, sha256 over every record's metadata and image digest).
    """
    refs = parent.refs
    n_places = place_count(refs)
    place_index = {n: i for i, n in enumerate(refs.names[:n_places])}
    logs_col = refs.meta.get("exp_log")
    stored: set[tuple[str, str]] = set()
    if logs_col is not None:
        stored = {(str(logs_col[r]), refs.sha256[r]) for r in range(n_places, len(refs))}
    taken = set(refs.names)
    gates = dict.fromkeys(GATES, 0)
    seen: set[tuple[str, int]] = set()
    logs: dict[str, None] = {}
    out: list[_Candidate] = []
    job = hashlib.sha256()
    n = 0
    for rec in records:
        n += 1
        logs.setdefault(rec.log, None)
        sha = hashlib.sha256(rec.image).hexdigest()
        fields = (rec.log, rec.seq, sha, rec.place_name, rec.p_correct, rec.vehicle)
        job.update(json.dumps([*fields, rec.timestamp, rec.index_version]).encode())
        key = (rec.log, int(rec.seq))
        if key in seen or (rec.log, sha) in stored:
            gates["already_merged"] += 1
            continue
        seen.add(key)
        lead = rec.mode == "lead"
        if not lead and not rec.p_correct >= settings.min_p_correct:  # NaN fails too
            gates["below_p_correct"] += 1
            continue
        place = place_index.get(rec.place_name)
        if place is None:
            gates["unknown_place"] += 1
            continue
        if probe_image(rec.image) is not None:
            gates["unreadable"] += 1
            continue
        stem = f"exp-{_tag(rec.log)}-{int(rec.seq):06d}"
        ext = _extension(rec.image, rec.content_type)
        name, k = stem + ext, 1
        while name in taken:
            k += 1
            name = f"{stem}-{k}{ext}"
        taken.add(name)
        out.append(
            _Candidate(
                rec.log,
                int(rec.seq),
                sha,
                place,
                name,
                float(rec.p_correct),
                rec.vehicle,
                rec.index_version,
                float(rec.timestamp),
                lead,
            )
        )
    return out, gates, n, list(logs), job.hexdigest()


def _write_frames(
    records: Iterable[FrameRecord],
    candidates: Sequence[_Candidate],
    folder: Path,
    parent: IndexReader,
) -> tuple[list[Path], list[dict[str, Any] | None]]:
    """Second pass: each candidate's bytes as a file in ``folder`` (written whole: a temporary
    file renamed; one left by an interrupted run is kept when its bytes are the same), and its
    recorded features when the log holds some that the methods of ``parent`` (the
    :class:`~hmpf.index.reader.IndexReader` merged into) extracted, laid out as its stored
    rows are (:func:`hmpf.features.unpack_features`, :func:`_same_layout`; None: to be
    extracted).

    Raises:
        IndexBuildError: a record read in the first pass is gone or changed.
    """
    folder.mkdir(parents=True, exist_ok=True)
    want = {(c.log, c.seq): c for c in candidates}
    paths: dict[tuple[str, int], Path] = {}
    recorded: dict[tuple[str, int], dict[str, Any] | None] = {}
    stored: dict[str, dict[str, np.ndarray]] | None = None
    methods = parent.methods
    for rec in records:
        c = want.get((rec.log, int(rec.seq)))
        if c is None or (c.log, c.seq) in paths:
            continue
        if hashlib.sha256(rec.image).hexdigest() != c.sha256:
            raise IndexBuildError(_changed(c))
        path = folder / c.name
        if not (path.is_file() and path.stat().st_size == len(rec.image)):
            tmp = path.with_name(f".{c.name}.{os.getpid()}.tmp")
            tmp.write_bytes(rec.image)
            os.replace(tmp, path)
        paths[(c.log, c.seq)] = path
        feats = None if rec.features is None else unpack_features(methods, rec.features)
        if feats is not None:
            stored = stored or _stored_layout(parent)
            feats = feats if _same_layout(methods, stored, feats) else None
        recorded[(c.log, c.seq)] = feats
    missing = [c for c in candidates if (c.log, c.seq) not in paths]
    if missing:
        raise IndexBuildError(_changed(missing[0]))
    keys = [(c.log, c.seq) for c in candidates]
    return [paths[k] for k in keys], [recorded[k] for k in keys]


def _stored_layout(parent: IndexReader) -> dict[str, dict[str, np.ndarray]]:
    """Each method's arrays of the version's first row: what a recorded feature must look
    like (:func:`_same_layout`)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for mid, m in parent.methods.items():
        if m.kind == "global":
            first: Any = np.asarray(parent.global_matrix(mid)[0:1])[0]
        else:
            (first,) = parent.local_features(mid, np.zeros(1, np.int64))
        out[mid] = {k: np.asarray(v) for k, v in m.to_arrays(first).items()}
    return out


def _same_layout(
    methods: Mapping[str, Method],
    stored: Mapping[str, Mapping[str, np.ndarray]],
    feats: Mapping[str, Any],
) -> bool:
    """Whether every recorded feature has the stored rows' arrays: the same names, dtypes,
    dimensions and sizes but along the first axis (a count of keypoints or regions), and
    finite values. The
    packed methods' keys already match; this keeps bytes crafted or damaged to fit the keys
    out of the version (they are extracted instead)."""
    for mid, m in methods.items():
        got = {k: np.asarray(v) for k, v in m.to_arrays(feats[mid]).items()}
        want = stored[mid]
        if got.keys() != want.keys():
            return False
        for k, w in want.items():
            g = got[k]
            if g.dtype != w.dtype or g.ndim != w.ndim or g.shape[1:] != w.shape[1:]:
                return False
            if m.kind == "global" and g.shape != w.shape:
                return False
            if g.dtype.kind == "f" and not np.isfinite(g).all():
                return False
    return True


def _features(
    paths: list[Path],
    recorded: Sequence[dict[str, Any] | None],
    methods: Mapping[str, Method],
    work: WorkDir,
    opt: BuildOptions,
) -> tuple[dict[str, list[Any]], int, int]:
    """Every candidate's features: the recorded ones as they are, the others extracted by
    the build's extraction (:func:`indexer.build._extract`).

    Returns:
        features per method id (in candidate order), images whose extraction an interrupted
        run had finished, and how many came from the log.
    """
    todo = [i for i, f in enumerate(recorded) if f is None]
    extracted: dict[str, list[Any]] = {mid: [] for mid in methods}
    resumed = 0
    if todo:
        extracted, resumed = _extract([paths[i] for i in todo], methods, work, opt)
    at = {i: j for j, i in enumerate(todo)}
    out = {
        mid: [extracted[mid][at[i]] if f is None else f[mid] for i, f in enumerate(recorded)]
        for mid in methods
    }
    return out, resumed, len(recorded) - len(todo)


def _changed(c: _Candidate) -> str:
    return (
        f"experience log {c.log!r} changed while it was merged (record {c.seq} is gone or "
        "differs); rerun the merge"
    )


# -- the gates that need features ------------------------------------------------------------
def _tier1_descriptor(parent: IndexReader) -> str | None:
    """The method whose descriptor near-duplicates and diversity are judged on: the first
    global method of tier 1 (else of any tier); None without a global method."""
    ids = [*parent.config.tiers[0].methods, *parent.config.method_ids]
    return next((m for m in ids if parent.methods[m].kind == "global"), None)


def _unit_rows(x: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length (cosine similarity is then a dot product)."""
    x = np.asarray(x, dtype=np.float64)
    x = x if x.ndim == 2 else x.reshape(x.shape[0], -1)
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.where(norm > 0, norm, 1.0)


def _place_routes(refs: RefTable, n_places: int) -> RouteMap:
    """The places' routes (``sequence``, ordered by ``timestamp`` where given; the whole map
    one route in index order without them), from the places' own rows."""
    meta = refs.meta
    seq, ts = meta.get("sequence"), meta.get("timestamp")
    return RouteMap.from_metadata(
        n_places,
        sequence=None if seq is None else seq[:n_places],
        timestamp=None if ts is None else ts[:n_places],
    )


def between_neighbours(
    candidates: Sequence[_Candidate], routes: RouteMap
) -> tuple[list[_Candidate], int]:
    """The candidates, each placed between its time neighbours where they say where it was;
    and how many were moved.

    A frame's neighbours are the candidates just before and after it of the same log and
    vehicle, by time (``_Candidate.time``; the record order breaks ties). When both steps to
    them are at most :data:`MAX_NEIGHBOUR_GAP_S` seconds and about equal
    (:data:`NEIGHBOUR_STEP_TOLERANCE`), the neighbours lie on one route ``2 m`` places apart
    (``m >= 1``: the vehicle moved at a constant pace), and the frame's place is on that
    route one place from the place midway between them, the frame is placed midway. The
    places used are the recorded ones (a moved frame does not move its neighbours).

    Why: a recorder's answers jitter by a place along a route (on Gardens Point, day_right's
    frames against the day_left map answer the place before about a third of the time, so
    two frames land on one place and the place after them holds no experience of the
    drive); where the vehicle's pace is steady, the midpoint of its neighbours is the better
    estimate. Frames of a vehicle standing still (neighbours at one place), of uneven steps,
    or at a route's end are left where they were recorded.
    """
    out = list(candidates)
    groups: dict[tuple[str, str], list[int]] = {}
    for i, c in enumerate(candidates):
        if math.isfinite(c.time) and not c.lead:  # a lead frame's place is a guess
            groups.setdefault((c.log, c.vehicle), []).append(i)
    moved = 0
    for members in groups.values():
        members.sort(key=lambda i: (candidates[i].time, candidates[i].seq))
        for a, i, b in zip(members, members[1:], members[2:], strict=False):
            before, here, after = candidates[a], candidates[i], candidates[b]
            step1, step2 = here.time - before.time, after.time - here.time
            longest = max(step1, step2)
            if min(step1, step2) <= 0 or longest > MAX_NEIGHBOUR_GAP_S:
                continue
            if abs(step1 - step2) > NEIGHBOUR_STEP_TOLERANCE * longest:
                continue
            route = routes.route_of[before.place]
            if routes.route_of[after.place] != route or routes.route_of[here.place] != route:
                continue
            ra, rb = int(routes.rank[before.place]), int(routes.rank[after.place])
            if ra == rb or (rb - ra) % 2:
                continue
            mid = (ra + rb) // 2
            if abs(int(routes.rank[here.place]) - mid) == 1:
                out[i] = dataclasses.replace(here, place=int(routes.ordered[mid]))
                moved += 1
    return out, moved


def place_leads(
    candidates: Sequence[_Candidate], routes: RouteMap
) -> tuple[list[_Candidate], int, int]:
    """The candidates with each lead frame placed from the frames after it, those it cannot
    place left out; (candidates, leads placed, leads left out).

    A lead frame (``_Candidate.lead``: recorded by the service just before a frame of the
    same vehicle that it recorded for its answer) carries its own answer's place, which the
    filter was not sure of. Its vehicle's frames that are not leads (same log and vehicle)
    after it in time give its place: the first of them, at most :data:`MAX_NEIGHBOUR_GAP_S`
    seconds after it, and up to :data:`LEAD_PACE_FRAMES` in all that follow each other within
    that gap on the first one's route (at least two) give the pace (places per second, from
    the first to the last); the lead frame is placed that pace times its time before the
    first one back along the route, rounded half away from zero. It is left out when there
    are not two such frames, when the time from the first to the last is zero, when the
    place would lie outside the route (a vehicle that joined the route at its start from off
    the map), or when the frame's own answer (its recorded place, which the service gave it
    then) is not on that route within :data:`LEAD_AGREEMENT` places of it: the pace and the
    frame's own evidence must agree (a recorded frame a place or two off, or a slow apparent
    pace, would otherwise carry its error back to the lead). The gates after this (agreement
    first) judge it like any frame.
    """
    follows: dict[tuple[str, str], list[_Candidate]] = {}
    for c in candidates:
        if not c.lead and math.isfinite(c.time):
            follows.setdefault((c.log, c.vehicle), []).append(c)
    for group in follows.values():
        group.sort(key=lambda c: (c.time, c.seq))
    out: list[_Candidate] = []
    placed = left = 0
    for c in candidates:
        if not c.lead:
            out.append(c)
            continue
        place = _lead_place(c, follows.get((c.log, c.vehicle), []), routes)
        if place is None:
            left += 1
            continue
        out.append(dataclasses.replace(c, place=place))
        placed += 1
    return out, placed, left


def _lead_place(lead: _Candidate, group: Sequence[_Candidate], routes: RouteMap) -> int | None:
    """Where ``lead`` was by the frames of ``group`` (its vehicle's, by time) after it."""
    if not math.isfinite(lead.time):
        return None
    after = [c for c in group if c.time > lead.time]
    if not after or after[0].time - lead.time > MAX_NEIGHBOUR_GAP_S:
        return None
    first = after[0]
    route = int(routes.route_of[first.place])
    run = [first]
    for c in after[1:LEAD_PACE_FRAMES]:
        if c.time - run[-1].time > MAX_NEIGHBOUR_GAP_S or routes.route_of[c.place] != route:
            break
        run.append(c)
    span = run[-1].time - first.time
    if len(run) < 2 or span <= 0:
        return None
    start = int(routes.rank[first.place])
    pace = (int(routes.rank[run[-1].place]) - start) / span
    back = pace * (first.time - lead.time)
    rank = start - int(math.copysign(math.floor(abs(back) + 0.5), back))  # half away from 0
    if not routes.route_start[route] <= rank < routes.route_end[route]:
        return None
    place = int(routes.ordered[rank])
    if float(routes.separation(place, lead.place)) > LEAD_AGREEMENT:
        return None
    return place


def _localise(
    parent: IndexReader,
    hierarchy: Hierarchy,
    features: Mapping[str, Sequence[Any]],
    i: int,
    place_of: np.ndarray,
) -> int:
    """The place frame ``i`` is localised at on its own (its features as a query). The
    reader's count is places where it groups experiences, else rows (mapped to places)."""
    query = {mid: features[mid][i] for mid in parent.methods}
    match = hierarchy.run(parent.scorer(query), parent.n).match
    return int(match) if parent.n != len(place_of) else int(place_of[match])


def _agreement(
    parent: IndexReader,
    candidates: Sequence[_Candidate],
    features: Mapping[str, Sequence[Any]],
    window: int | None,
) -> tuple[list[int], list[str]]:
    """The candidates (indices) whose own localisation lands within ``window`` places of the
    recorded place along its route, and lines naming the first ones that do not."""
    if window is None:
        return list(range(len(candidates))), []
    refs = parent.refs
    n_places = place_count(refs)
    routes = _place_routes(refs, n_places)
    place_col = refs.meta.get("place")
    place_of = np.arange(len(refs), dtype=np.int64)
    if place_col is not None:
        place_of[n_places:] = np.asarray(place_col[n_places:], dtype=np.int64)
    hierarchy = parent.hierarchy()
    ok: list[int] = []
    rejected: list[str] = []
    for i, c in enumerate(candidates):
        found = _localise(parent, hierarchy, features, i, place_of)
        gap = float(routes.separation(found, c.place))
        if gap <= window:
            ok.append(i)
        elif len(rejected) < MAX_LISTED:
            off = "another route" if math.isinf(gap) else f"{int(gap)} places away"
            rejected.append(
                f"disagreeing {c.name}: recorded at {refs.names[c.place]}, localised at "
                f"{refs.names[found]} ({off})"
            )
    return ok, rejected


def _diverse(
    candidates: Sequence[int],
    vectors: np.ndarray,
    held: np.ndarray,
    settings: ExperienceSettings,
) -> tuple[list[int], list[int], list[int]]:
    """One place's duplicate and cap gates.

    Args:
        candidates: indices into ``vectors`` (unit rows), in record order.
        held: (h, D) unit descriptors of the images the place holds already.

    Returns:
        (kept, duplicates, over the cap), indices of ``candidates``' values.
    """
    ref = [held[j] for j in range(len(held))]
    fresh, dups = [], []
    limit = settings.duplicate_similarity
    for i in candidates:
        v = vectors[i]
        if limit is not None and ref and float(np.max(np.stack(ref) @ v)) >= limit:
            dups.append(i)
            continue
        fresh.append(i)
        ref.append(v)
    cap = settings.max_per_place
    slots = len(fresh) if cap is None else max(0, cap - len(held))
    if len(fresh) <= slots:
        return fresh, dups, []
    # greedy farthest point: each pick is the frame least similar to everything held/picked
    near = np.max(vectors[fresh] @ held.T, axis=1) if len(held) else np.full(len(fresh), -np.inf)
    chosen: list[int] = []
    for _ in range(slots):
        best = int(np.argmin(np.where(np.isin(fresh, chosen), np.inf, near)))
        chosen.append(fresh[best])
        near = np.maximum(near, vectors[fresh] @ vectors[fresh[best]])
    kept = [i for i in fresh if i in chosen]  # record order
    return kept, dups, [i for i in fresh if i not in chosen]


def _diversity_gates(
    parent: IndexReader,
    candidates: Sequence[_Candidate],
    agreeing: Sequence[int],
    features: Mapping[str, Sequence[Any]],
    settings: ExperienceSettings,
) -> tuple[list[int], int, int]:
    """The duplicate and cap gates over the agreeing candidates, place by place.

    Returns:
        (kept candidate indices in record order, duplicates, over the cap).
    """
    mid = _tier1_descriptor(parent)
    refs = parent.refs
    n_places = place_count(refs)
    by_place: dict[int, list[int]] = {}
    for i in agreeing:
        by_place.setdefault(candidates[i].place, []).append(i)
    vectors = stored = np.zeros((0, 1))
    if mid is not None:  # else no descriptor to compare: no duplicates, the cap keeps the first
        vectors = _unit_rows(_global_rows(parent.methods[mid], features[mid]))
        stored = _unit_rows(np.asarray(parent.columns(mid)))
    place_col = refs.meta.get("place")
    held_rows: dict[int, list[int]] = {p: [p] for p in by_place}
    if place_col is not None:
        for r in range(n_places, len(refs)):
            p = int(place_col[r])
            if p in held_rows:
                held_rows[p].append(r)
    kept: list[int] = []
    n_dup = n_cap = 0
    for p, idx in by_place.items():
        if mid is None:
            cap = settings.max_per_place
            slots = len(idx) if cap is None else max(0, cap - len(held_rows[p]))
            kept += idx[:slots]
            n_cap += len(idx[slots:])
            continue
        k, d, c = _diverse(idx, vectors, stored[held_rows[p]], settings)
        kept += k
        n_dup += len(d)
        n_cap += len(c)
    return sorted(kept), n_dup, n_cap


def _global_rows(method: Method, features: Sequence[Any]) -> np.ndarray:
    cols = columns_from_features(method, list(features))
    assert isinstance(cols, np.ndarray)
    return cols


# -- the merge -------------------------------------------------------------------------------
def merge(
    index: str | Path,
    records: Iterable[FrameRecord],
    *,
    settings: Mapping[str, Any] | None = None,
    gates: bool = True,
    options: BuildOptions | None = None,
    dry_run: bool = False,
    resume: bool = False,
) -> MergeReport:
    """Merge recorded frames into a new version of the index at ``index`` (see the module
    docstring), or with ``dry_run`` only say what would be added (nothing is written to the
    index: the frames and features go to a temporary folder).

    Args:
        records: the frames, in log order (read twice: a list, or a re-readable collection
            such as the logs' records; a one-shot iterator is read into a list).
        settings: :class:`~hmpf.config.ExperienceSettings` fields over the config's section.
        gates: False opens every gate (confidence, agreement, duplicates, cap): each readable
            frame of a known place, not merged before, is added.
        options: extraction (workers, Ray, progress) and FAISS overrides; storage otherwise
            as the current version's.

    Returns:
        the report; ``version`` None when nothing was published (dry run, or no frame left).

    Raises:
        IndexBuildError, IndexCorruptError, DatasetError: bad input or a current version
            that does not verify (nothing is written); ImageError never (unreadable frames
            are a gate).
    """
    started = time.perf_counter()
    records = _repeatable(records)
    root = Path(index)
    if dry_run:
        with (
            _parent(root, "merge") as parent,
            tempfile.TemporaryDirectory(prefix="hmpf-merge-") as tmp,
        ):
            chosen = resolve_settings(parent.config.experience_settings, settings, gates)
            return _run(parent, records, chosen, options, WorkDir(Path(tmp)), started, None)
    tx = VersionTransaction(root, "merge")
    with tx, _parent(tx.root, "merge") as parent:
        chosen = resolve_settings(parent.config.experience_settings, settings, gates)
        return _run(parent, records, chosen, options, tx.work, started, (tx, resume))


def _run(
    parent: IndexReader,
    records: Iterable[FrameRecord],
    settings: ExperienceSettings,
    options: BuildOptions | None,
    work: WorkDir,
    started: float,
    publish: tuple[VersionTransaction, bool] | None,
) -> MergeReport:
    """The merge against ``parent`` in ``work``; publishes through ``publish`` (None: a dry
    run)."""
    opt = _parent_options(parent, options or BuildOptions(progress=False))
    candidates, counts, n_records, logs, digest = _screen(parent, records, settings)
    routes = _place_routes(parent.refs, place_count(parent.refs))
    moved = placed = 0
    if settings.interpolate_places:
        candidates, moved = between_neighbours(candidates, routes)
    if settings.place_leads:
        candidates, placed, counts["unplaced"] = place_leads(candidates, routes)
    else:
        counts["unplaced"] = sum(c.lead for c in candidates)
        candidates = [c for c in candidates if not c.lead]
    if publish is None:
        work.path.mkdir(parents=True)
    else:
        tx, resume = publish
        job = {
            "operation": "merge",
            "config": parent.config.digest(),
            "parent": parent.version,
            "records": digest,
            "settings": settings.model_dump(),
            "options": opt.identity(),
        }
        tx.begin(job, resume)
    paths, recorded = _write_frames(records, candidates, work.path / "frames", parent)
    features, resumed, n_recorded = _features(paths, recorded, parent.methods, work, opt)
    agreeing, rejected = _agreement(parent, candidates, features, settings.agreement_window)
    counts["disagreeing"] = len(candidates) - len(agreeing)
    kept, counts["duplicate"], counts["over_cap"] = _diversity_gates(
        parent, candidates, agreeing, features, settings
    )
    n_places = place_count(parent.refs)
    per_place: dict[int, int] = {}
    for i in kept:
        per_place[candidates[i].place] = per_place.get(candidates[i].place, 0) + 1
    report = MergeReport(
        logs=logs,
        records=n_records,
        gates=counts,
        added=len(kept),
        frames_extracted=len(candidates) - n_recorded,
        features_recorded=n_recorded,
        interpolated=moved,
        leads_placed=placed,
        seconds=time.perf_counter() - started,
        settings=settings.model_dump(),
        dry_run=publish is None,
        parent=parent.version,
        added_per_place=per_place,
        rejected_agreement=rejected,
        places={"count": n_places, "experiences": len(parent.refs) - n_places + len(kept)},
    )
    if publish is None:
        return report
    if not kept:
        work.discard()
        return report
    new_rows = _experience_rows([candidates[i] for i in kept])
    kept_paths = [paths[i] for i in kept]
    cols = {
        mid: concat_columns(
            parent.columns(mid), columns_from_features(m, [features[mid][i] for i in kept])
        )
        for mid, m in parent.methods.items()
    }
    thumbs = Ragged.concat([_row_thumbnails(parent), _thumbnails(kept_paths, new_rows, work)])
    version = NewVersion(
        parent.config,
        parent.methods,
        parent.refs.concat(new_rows),
        cols,
        opt,
        parent,
        retrain=False,
        thumbnails=thumbs,
        report=report.to_json(),
    )
    report.summary = publish[0].publish(
        version, extracted=len(kept), resumed=min(resumed, len(kept))
    )
    report.version = report.summary.version
    return report


def _experience_rows(kept: Sequence[_Candidate]) -> RefTable:
    """The reference table of the experience rows: names, digests, place and provenance."""
    meta = {
        "place": np.array([c.place for c in kept], dtype=np.float64),
        "exp_log": np.array([c.log for c in kept], dtype=object),
        "exp_vehicle": np.array([c.vehicle for c in kept], dtype=object),
        "exp_version": np.array([c.version for c in kept], dtype=object),
        "exp_time": np.array([c.time for c in kept], dtype=np.float64),
        "exp_p_correct": np.array([c.p_correct for c in kept], dtype=np.float64),
    }
    return RefTable([c.name for c in kept], [c.sha256 for c in kept], meta, [""] * len(kept))


# -- removal by provenance -------------------------------------------------------------------
_FILTER_KEYS = ("vehicle", "log", "before")


def parse_filters(filters: Sequence[str]) -> dict[str, list[str | float]]:
    """``["vehicle=v1", "before=2025-01-01"]`` -> ``{"vehicle": ["v1"], "before": [t]}``
    (``before``: seconds since the epoch, or ISO 8601 text).

    Raises:
        DatasetError: no filter, or one that is not ``vehicle=``, ``log=`` or ``before=``.
    """
    if not filters:
        raise DatasetError("--experiences-from needs at least one of vehicle=V, log=L, before=T")
    out: dict[str, list[str | float]] = {}
    for text in filters:
        key, sep, value = text.partition("=")
        key = key.strip()
        if not sep or key not in _FILTER_KEYS:
            raise DatasetError(
                f"--experiences-from {text!r}: expected vehicle=V, log=L or before=TIME"
            )
        out.setdefault(key, []).append(_before(value) if key == "before" else value)
    return out


def _before(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        pass
    try:
        return datetime.fromisoformat(text.strip()).timestamp()
    except ValueError:
        raise DatasetError(
            f"--experiences-from before={text!r}: neither seconds since the epoch nor ISO 8601"
        ) from None


def _matching(refs: RefTable, filters: Mapping[str, Sequence[str | float]]) -> np.ndarray:
    """(N,) the experience rows that match every key of ``filters`` (any value of a key)."""
    n_places = place_count(refs)
    hit = np.zeros(len(refs), dtype=bool)
    hit[n_places:] = True
    meta = refs.meta
    for key, values in filters.items():
        if key == "before":
            t = np.asarray(meta.get("exp_time", np.full(len(refs), np.nan)), dtype=np.float64)
            hit &= t < max(float(v) for v in values)
        else:
            col = meta.get(f"exp_{key}", np.full(len(refs), "", dtype=object))
            hit &= np.isin(col.astype(str), [str(v) for v in values])
    return hit


def remove_experiences(
    index: str | Path, filters: Sequence[str], *, options: BuildOptions | None = None
) -> Summary:
    """Publish a version of the current one without the experiences matching ``filters``
    (:func:`parse_filters`; values of one key are alternatives, different keys must all
    match). Places are never removed.

    Raises:
        DatasetError: a bad filter. IndexBuildError: no experience matches.
    """
    parsed = parse_filters(filters)
    tx = VersionTransaction(Path(index), "remove")
    with tx, _parent(tx.root, "remove") as parent:
        refs = parent.refs
        n_places = place_count(refs)
        hit = _matching(refs, parsed)
        if not hit.any():
            raise IndexBuildError(_nothing_matches(parent, filters, n_places))
        keep = np.flatnonzero(~hit).astype(np.int64)
        new_refs = without_empty_experiences(refs.select(keep))
        left = len(keep) - n_places
        report = {
            "operation": "remove",
            "filters": list(filters),
            "removed": int(hit.sum()),
            "places": {"count": n_places, "experiences": left},
        }
        tx.begin(
            {
                "operation": "remove-experiences",
                "parent": parent.version,
                "filters": report["filters"],
            }
        )
        new = NewVersion(
            parent.config,
            parent.methods,
            new_refs,
            {mid: select_columns(parent.columns(mid), keep) for mid in parent.methods},
            _parent_options(parent, options),
            parent,
            retrain=False,
            thumbnails=None if parent.thumbnails is None else _row_thumbnails(parent).select(keep),
            report=report,
        )
        return tx.publish(new, extracted=0)


def _nothing_matches(parent: IndexReader, filters: Sequence[str], n_places: int) -> str:
    refs = parent.refs
    n_exp = len(refs) - n_places
    if n_exp == 0:
        return f"{parent.version} holds no experiences; nothing to remove"
    vehicles = sorted(set(map(str, refs.meta.get("exp_vehicle", [])[n_places:])))
    logs = sorted(set(map(str, refs.meta.get("exp_log", [])[n_places:])))
    return (
        f"no experience of {parent.version} matches {' and '.join(filters)}; its {n_exp} "
        f"experience(s) come from vehicle(s) {', '.join(map(repr, vehicles[:10]))} and "
        f"log(s) {', '.join(logs[:10])}"
    )
