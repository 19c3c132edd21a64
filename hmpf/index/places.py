"""Places and their experiences: what the hierarchy runs over in a version with fleet frames.

A version's reference rows are the places' original references first (row ``p`` is place
``p``), then *experiences*: further images of a place (frames from the fleet, in another
light or season), whose ``place`` column names the place
(:data:`hmpf.index.tables.EXPERIENCE_COLUMNS`).
Candidates, answers, routes and ground truth are places, so adding experiences never
crowds a tier's top k with two images of one place, never shares a place's normalisation
between its experiences and never changes what a right answer is.

* :class:`Places`: the grouping (which rows belong to which place), checked against the
  format's invariant when read.
* :class:`PlaceScorer`: a place scores by its best experience, per method: the raw scores of
  its rows reduced (max for a similarity, min for a distance) *before* the hierarchy
  normalises them; it remembers which row won, so an answer can say which experience matched.
  Each *experience set* (one log, vehicle and day: one drive's conditions,
  :func:`experience_sets`) is first shifted to the original references' score level for the
  query, by its experiences' differences from their own places' originals
  (:func:`align_pairs`), so that images taken in the query's own conditions do not attract
  it whatever place they show; and a place's best is lessened by what its extra images are
  expected to add by chance, so that places with experiences do not outrank the others by
  their number. The tiers after the first score each place by one image, the one tier 1
  found best (:meth:`PlaceScorer.representatives`).
* :class:`Experience`: one row described for an answer (name, original or fleet, provenance).
* :func:`route_map_of`, :func:`places_profile`: the places' routes and reference profile, as
  the reader computes them at load and the indexer when it writes a version.

Pure numpy; the reader (:class:`hmpf.index.reader.IndexReader`) wires them to an index.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hmpf.confidence import ReferenceProfile
from hmpf.config import HierarchyConfig
from hmpf.hierarchy import ScoreFn
from hmpf.index.layout import IndexCorruptError
from hmpf.index.rows import DiskRows
from hmpf.index.tables import RefTable, _ranges
from hmpf.methods import Method
from hmpf.sequence import RouteMap

__all__ = [
    "Experience",
    "PlaceScorer",
    "Places",
    "SetAlignment",
    "align_pairs",
    "pair_sample",
    "augment_rows",
    "experience_of_row",
    "experience_sets",
    "place_scorer",
    "places_profile",
    "reduce_rows",
    "route_map_of",
]


@dataclass(frozen=True)
class Places:
    """Which rows of a version belong to which place.

    Attributes:
        n: number of places P (rows ``0 .. P-1`` are their original references).
        place_of: (N,) int64, the place of every row (``place_of[p] == p`` for ``p < P``).
        order: (N,) int64, the rows grouped by place: place ``p``'s rows are
            ``order[starts[p]:starts[p + 1]]``, its original reference first, then its
            experiences in row order.
        starts: (P + 1,) int64 offsets into ``order``.
    """

    n: int
    place_of: np.ndarray
    order: np.ndarray
    starts: np.ndarray

    @classmethod
    def identity(cls, n: int) -> Places:
        """``n`` places of one experience each (a version without experiences)."""
        rows = np.arange(n, dtype=np.int64)
        return cls(n, rows, rows, np.arange(n + 1, dtype=np.int64))

    @classmethod
    def from_column(cls, place: np.ndarray | None, n_rows: int, where: str = "") -> Places:
        """The grouping a ``place`` column gives (None: no column, one experience per place).

        Args:
            place: (N,) float, NaN on an original reference, the place's index on an
                experience.
            n_rows: N, the version's rows.
            where: the file the column was read from (named in errors).

        Raises:
            IndexCorruptError: the column breaks the format's invariant (an original after an
                experience, a place that is not an original reference's row, a fraction), so
                answers would name the wrong place.
        """
        if place is None:
            return cls.identity(n_rows)
        col = np.asarray(place, dtype=np.float64)
        if col.shape != (n_rows,):
            raise IndexCorruptError(f"{where}: meta/place has {col.shape}, expected ({n_rows},)")
        original = np.isnan(col)
        p = int(np.argmin(original)) if not original.all() else n_rows
        if original[p:].any():
            bad = p + int(np.argmax(original[p:]))
            raise IndexCorruptError(
                f"{where}: meta/place: row {bad} is an original reference after experience row "
                f"{p}; original references must come first"
            )
        exp = col[p:]
        wrong = ~((exp >= 0) & (exp < p) & (exp == np.floor(exp)))
        if wrong.any():
            bad = p + int(np.argmax(wrong))
            raise IndexCorruptError(
                f"{where}: meta/place: experience row {bad} names place "
                f"{float(col[bad])!r}, which is not one of the {p} places (0 .. {p - 1})"
            )
        place_of = np.concatenate([np.arange(p, dtype=np.int64), exp.astype(np.int64)])
        order = np.argsort(place_of, kind="stable").astype(np.int64)
        counts = np.bincount(place_of, minlength=p)
        starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return cls(p, place_of, order, starts)

    @property
    def n_rows(self) -> int:
        return len(self.place_of)

    @property
    def has_experiences(self) -> bool:
        """Whether some place has more than its original reference."""
        return self.n_rows > self.n

    def counts(self, places: np.ndarray | None = None) -> np.ndarray:
        """Rows per place (of ``places``, default every place)."""
        c = np.diff(self.starts)
        return c if places is None else c[np.asarray(places, dtype=np.int64)]

    def rows(self, place: int) -> np.ndarray:
        """The rows of one place: its original reference first, then its experiences."""
        return self.order[self.starts[place] : self.starts[place + 1]]

    def expand(self, places: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rows of ``places`` (in that order, each place's rows together) and the offset of
        each place's first row among them (what ``reduceat`` takes)."""
        idx = np.asarray(places, dtype=np.int64)
        counts = self.counts(idx)
        rows = self.order[_ranges(self.starts[idx], counts)]
        return rows, np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def augments(method: Method) -> bool:
    """Whether a global method's searched rows differ from its stored ones (``dba``: its
    route augmentation averages neighbours, so the searched matrix is made at load)."""
    return bool(int(getattr(method.config, "dba", 0) or 0))


def augment_rows(method: Method, stored: np.ndarray, places: Places) -> np.ndarray:
    """The searched matrix of a global method over every row (its route augmentation,
    :meth:`~hmpf.methods.base.GlobalMethod.augment_references`, ``dba``).

    The augmentation averages route neighbours, and the route is the places' order: the
    original references are augmented among themselves exactly as in a version without
    experiences, and an experience of place ``p`` as if it stood at ``p`` (its place's
    route neighbours around it), never with the unrelated rows stored next to it.
    """
    augment = method.augment_references  # type: ignore[attr-defined]
    P = places.n
    if not places.has_experiences:
        return augment(stored)
    head = np.asarray(augment(stored[:P]))
    k = int(getattr(method.config, "dba", 0) or 0)
    if k == 0:
        return np.concatenate([head, np.asarray(stored[P:]).astype(head.dtype)])
    out = np.empty((places.n_rows, *head.shape[1:]), dtype=head.dtype)
    out[:P] = head
    for r in range(P, places.n_rows):
        p = int(places.place_of[r])
        lo, hi = max(0, p - k), min(P, p + k + 1)
        window = np.array(stored[lo:hi])
        window[p - lo] = stored[r]
        out[r] = np.asarray(augment(window))[p - lo]
    return out


def reduce_rows(
    raw: np.ndarray, rows: np.ndarray, seg: np.ndarray, higher_is_better: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Per segment of ``raw`` (segments start at ``seg``, none empty): the best value and the
    row (of ``rows``) that has it.

    The best is the max for a similarity, the min for a distance; NaN counts only where a
    segment holds nothing else (then the segment's first row wins), and ties go to the
    earlier entry (a place's original reference before its experiences).
    """
    vals = np.asarray(raw)
    reduce = np.fmax if higher_is_better else np.fmin
    best = reduce.reduceat(vals, seg)
    counts = np.diff(np.append(seg, len(vals)))
    hit = vals == np.repeat(best, counts)
    pos = np.where(hit, np.arange(len(vals)), len(vals))
    first = np.minimum.reduceat(pos, seg)
    first = np.where(first == len(vals), seg, first)
    return best, rows[first]


def route_map_of(
    meta: Mapping[str, np.ndarray], n_places: int, config: HierarchyConfig
) -> RouteMap:
    """The mapped routes over a version's places (:mod:`hmpf.sequence`): the ``sequence``
    column's routes, ordered by ``timestamp`` where given, junctions from ``lat``/``lon``
    within the config's ``junction_m``; from the places' original references (rows
    ``0 .. n_places - 1`` of the metadata columns ``meta``)."""

    def col(name: str) -> np.ndarray | None:
        v = meta.get(name)
        return None if v is None else v[:n_places]

    return RouteMap.from_metadata(
        n_places,
        sequence=col("sequence"),
        timestamp=col("timestamp"),
        lat=col("lat"),
        lon=col("lon"),
        junction_m=config.sequence_params().junction_m,
    )


def places_profile(
    config: HierarchyConfig,
    methods: Mapping[str, Method],
    searched: Mapping[str, Any],
    routes: RouteMap,
) -> ReferenceProfile:
    """The places' :class:`~hmpf.confidence.ReferenceProfile` for the first tier's global
    methods (the default parameters, :func:`~hmpf.confidence.profile_params`): from each
    method's searched matrix (``searched``, after :func:`augment_rows`: an array, or rows
    read on demand; its first ``routes.n`` rows, the places' original references). Tier-1
    methods without a matrix in ``searched`` (local ones) are left out."""
    tier1 = config.tiers[0].methods
    db = {m: _first_rows(searched[m], routes.n) for m in tier1 if m in searched}
    return ReferenceProfile.build(methods, db, [m for m in tier1 if m in db], routes)


def _first_rows(matrix: Any, n: int) -> Any:
    """The first ``n`` rows, still on disk where ``matrix`` is (a million rows of NetVLAD do
    not fit in memory as float32)."""
    return matrix.head(n) if isinstance(matrix, DiskRows) else matrix[:n]


class PlaceScorer:
    """A :data:`~hmpf.hierarchy.ScoreFn` over places from one over rows (see
    :func:`place_scorer`).

    Attributes:
        winners: per method scored so far, (P,) int64: the row whose raw score the place
            got (-1: the place was not scored by that method for this query).
    """

    def __init__(
        self,
        row_fn: ScoreFn,
        places: Places,
        methods: Mapping[str, Method],
        sets: np.ndarray | None = None,
        pairs: np.ndarray | None = None,
    ) -> None:
        self.row_fn = row_fn
        self.places = places
        self.better = {mid: bool(m.higher_is_better) for mid, m in methods.items()}
        self.winners: dict[str, np.ndarray] = {}
        self.sets = sets
        self.n_sets = 0 if sets is None else int(sets.max()) + 1
        #: the experience rows a whole-database call aligns its sets on (:func:`pair_sample`)
        self.pairs = pairs if pairs is not None or sets is None else pair_sample(sets)
        #: per method scored over every row: each set's alignment from its sampled pairs
        self._whole: dict[str, dict[int, SetAlignment]] = {}
        #: per method scored over every row: each row's aligned score, robustly standardised
        self._z: dict[str, np.ndarray] = {}
        #: (P,) each place's representative row for the later tiers (:meth:`representatives`)
        self._rep: np.ndarray | None = None

    def __call__(self, mid: str, subset: np.ndarray | None) -> np.ndarray:
        pl = self.places
        if subset is None:
            full = np.asarray(self.row_fn(mid, None))
            rows, seg = pl.order, pl.starts[:-1]
            raw = full[rows]
            idx: np.ndarray | slice = slice(None)
        else:
            full = None
            idx = np.asarray(subset, dtype=np.int64)
            if len(idx) == 0:
                return np.asarray(self.row_fn(mid, idx))
            rows, seg = pl.expand(idx)
            raw = np.asarray(self.row_fn(mid, rows))
        if self.sets is None:
            best, won = reduce_rows(raw, rows, seg, self.better[mid])
        else:
            best, won = self._aligned_best(mid, raw, rows, seg, full)
        if mid not in self.winners:
            self.winners[mid] = np.full(pl.n, -1, dtype=np.int64)
        self.winners[mid][idx] = won
        return best

    def _aligned_best(
        self,
        mid: str,
        raw: np.ndarray,
        rows: np.ndarray,
        seg: np.ndarray,
        full: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per place (segment): the best of its rows once each experience set is aligned to
        the originals (:func:`align_pairs`), less the gain its extra images are expected to
        give it by chance; and the winning row. After a whole-database call, a later tier
        scores each place by its representative row alone (:meth:`representatives`).

        A call that scores every row (``full`` given) aligns each set on its sampled pairs
        (:attr:`pairs`) and keeps the figures. A later tier's call aligns each set on the
        candidates' own pairs (the places it compares: better than tier 1's figures for the
        same methods on the one Gardens Point scenario tried, a night pass over half the
        route); a set with fewer than :data:`MIN_PAIRS` pairs
        among them takes the method's whole-database figures where tier 1 scored it, else is
        scored as it is (measured on Gardens Point: the same recall as leaving it out, and a
        frame that is one of a few experiences is still answered with that experience)."""
        assert self.sets is not None and self.pairs is not None
        sign = 1.0 if self.better[mid] else -1.0
        v = sign * np.asarray(raw, dtype=np.float64)  # higher is better from here
        sets = self.sets[rows]
        if full is not None:
            f = sign * np.asarray(full, dtype=np.float64)
            pr = self.pairs
            stats = align_pairs(f[pr] - f[self.places.place_of[pr]], self.sets[pr])
            self._whole[mid] = stats
        else:
            counts = np.diff(np.append(seg, len(rows)))
            # each row against its place's original (the first row of its segment)
            found = align_pairs(v - np.repeat(v[seg], counts), sets)
            stats = {**self._whole.get(mid, {}), **found}
        # a set not placed (too few pairs) is scored as it is: it covers at most two of the
        # places compared
        shift, gain = np.zeros(self.n_sets), np.zeros(self.n_sets)
        for s, al in stats.items():
            shift[s], gain[s] = al.shift, al.gain
        v = v - shift[sets]
        if full is not None:
            self._z[mid] = _standardised(f - shift[self.sets])
            self._rep = None
        else:
            rep = self.representatives()
            if rep is not None:
                # one image per place: the one tier 1 found best; no chance gain to take back
                # (the others as NaN: a representative without a score leaves its place
                # unscored, as a one-image place's NaN does)
                v = np.where(rows == rep[self.places.place_of[rows]], v, np.nan)
                best, won = reduce_rows(v, rows, seg, True)
                return sign * best, won
        g = np.where(np.isfinite(v), gain[sets], 0.0)  # a NaN row adds nothing
        best, won = reduce_rows(v, rows, seg, True)
        return sign * (best - np.add.reduceat(g, seg)), won

    def representatives(self) -> np.ndarray | None:
        """(P,) per place, the row that stands for it in the tiers after the first: the one
        whose aligned scores of the methods that scored the whole database, each robustly
        standardised (:func:`_standardised`), sum highest. None before such a call (a
        hierarchy run under a GPS prior scores subsets only: every tier then takes a place's
        best image, less the chance gain).

        Why one image: the expensive later methods then compare the query with the image of
        each candidate place most like it, rather than each method taking its own best image
        of the place, which mixes evidence across images and lets a place's other images win
        by chance. On Gardens Point (default preset, night_right queries) this raised
        single-frame recall@1 with day_right experiences of every place in the day_left map;
        the *scenarios* of docs/results/experiences.md measure it."""
        if self._rep is None and self._z:
            z = np.sum(list(self._z.values()), axis=0)
            pl = self.places
            _, self._rep = reduce_rows(z[pl.order], pl.order, pl.starts[:-1], True)
        return self._rep

    def matched_rows(self, priority: Sequence[str]) -> np.ndarray:
        """(P,) per place the row that matched it for this query, -1 where no method scored
        it: the winner of the first method of ``priority`` that scored the place."""
        out = np.full(self.places.n, -1, dtype=np.int64)
        for mid in reversed(priority):
            w = self.winners.get(mid)
            if w is not None:
                out = np.where(w >= 0, w, out)
        return out


#: Rows whose aligned scores give a method's median and MAD in :func:`_standardised`.
Z_SAMPLE = 4096


def _standardised(x: np.ndarray) -> np.ndarray:
    """``(x - median) / MAD``, the median and MAD of up to :data:`Z_SAMPLE` evenly spaced
    entries (a fixed cost at any map size); NaN (and a zero MAD's infinities) as a very low
    value, so that such a row never stands for its place while it has another."""
    n = len(x)
    sample = x[_evenly_spaced(n, Z_SAMPLE)]
    sample = sample[np.isfinite(sample)]
    if not len(sample):
        return np.full(n, -1e9)
    med = float(np.median(sample))
    mad = float(np.median(np.abs(sample - med))) or 1.0
    return np.nan_to_num((x - med) / mad, nan=-1e9, posinf=1e9, neginf=-1e9)


#: Experience rows per set whose pairs place the set for a whole-database call
#: (:func:`pair_sample`): the median and the MAD of a few hundred pairs are as good as those
#: of all, and the work stays a fixed size however many experiences a map holds.
PAIR_SAMPLE = 256


def pair_sample(sets: np.ndarray) -> np.ndarray:
    """Up to :data:`PAIR_SAMPLE` experience rows of each set (every row of a smaller set),
    evenly spaced over the set's rows: the same for every query and method."""
    out = [np.zeros(0, dtype=np.int64)]
    order = np.argsort(sets, kind="stable")
    bounds = np.searchsorted(sets[order], np.arange(int(sets.max()) + 2))
    for s in range(1, len(bounds) - 1):
        rows = order[bounds[s] : bounds[s + 1]]
        if len(rows):
            out.append(rows[_evenly_spaced(len(rows), PAIR_SAMPLE)])
    return np.concatenate(out)


def _evenly_spaced(n: int, k: int) -> np.ndarray:
    """Up to ``k`` of the positions ``0 .. n-1``, evenly spaced, first and last included
    (every position when ``n <= k``)."""
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(np.int64))


@dataclass(frozen=True)
class SetAlignment:
    """How one experience set's raw scores stand against the original references' for one
    query and method (:func:`align_pairs`), in higher-is-better units.

    Attributes:
        shift: the median of its pairs' differences: what the set's conditions add to every
            score (subtracted from its rows).
        gain: the mean of ``max(0, difference - shift)``: what one extra image of this set
            adds to a place's best score by chance (subtracted from each place per image).
    """

    shift: float
    gain: float


#: The fewest pairs (an experience and its place's original, both scored) that place an
#: experience set for one query and method (:func:`align_pairs`).
MIN_PAIRS = 3

#: The expected positive part of a centred normal difference per unit of its median absolute
#: deviation: E[max(0, X)] = sigma / sqrt(2 pi) and MAD = 0.6745 sigma (:func:`align_pairs`).
GAIN_PER_MAD = 1.0 / (math.sqrt(2.0 * math.pi) * 0.6744897501960817)


def experience_sets(refs: RefTable, places: Places) -> np.ndarray | None:
    """(N,) int: 0 on the original references, ``1 .. S`` for the experience *sets*: the
    frames of one log, one vehicle and one day (by ``exp_time``), i.e. one drive's
    conditions. None for a version without experiences."""
    if not places.has_experiences:
        return None
    meta, n, n_rows = refs.meta, places.n, places.n_rows

    def column(name: str) -> np.ndarray:
        v = meta.get(name)
        return np.array([""] * n_rows, dtype=object) if v is None else np.asarray(v)

    logs, vehicles = column("exp_log"), column("exp_vehicle")
    times = np.asarray(meta.get("exp_time", np.full(n_rows, np.nan)), dtype=np.float64)
    days = np.where(np.isfinite(times), np.floor(times / 86400.0), -1.0)
    keys: dict[tuple[str, str, float], int] = {}
    out = np.zeros(n_rows, dtype=np.int64)
    for r in range(n, n_rows):
        key = (str(logs[r]), str(vehicles[r]), float(days[r]))
        out[r] = keys.setdefault(key, len(keys) + 1)
    return out


def align_pairs(diff: np.ndarray, sets: np.ndarray) -> dict[int, SetAlignment]:
    """Per experience set, its :class:`SetAlignment` for one query and method, from pairs.

    Why: a query scores every image taken in its own conditions higher (a night frame is
    closer to any night frame than to a day image of its own place). Each experience is
    compared with its own place's original reference, scored for the same query: the
    difference is what the set's conditions add plus noise, and only for the query's own
    place what the experience *shows* (a view the original lacks). The median difference
    over the set (the query's place is one of many) is the conditions' part: subtracted, the
    set stands at the originals' level and keeps what stands out within it.

    A place's best over its images is still lifted by chance: the best of two noisy draws
    beats one. ``gain`` is what one extra image adds on average to a place it does not show,
    the expected positive part of the centred differences, estimated from their median
    absolute deviation (:data:`GAIN_PER_MAD`, exact for normal noise): robust to the few
    differences that are real, such as the query's own place, which a mean of the positive
    parts would let dominate a small set. The scorer subtracts it per extra image, so a
    place with experiences does not outrank one without by their number.

    Why both, measured on Gardens Point (default preset; map day_left, night_right queries;
    a night pass over one half of the route merged at the frames' true places, the other
    half queried, :mod:`bench.experiences`' ``scenarios``): the per-set median shift over a
    sample of rows that this replaced pulled the queried half's night frames to the places
    the night pass covered (docs/results/experiences.md).

    Args:
        diff: (R,) per scored row, its raw score minus its place's original's, higher is
            better (0 on the originals themselves; NaN where either is NaN).
        sets: (R,) their experience sets (0: original).

    Returns:
        set id -> :class:`SetAlignment`, for every set with at least :data:`MIN_PAIRS`
        finite differences among the rows.
    """
    out: dict[int, SetAlignment] = {}
    for s in np.unique(sets[sets > 0]):
        d = np.asarray(diff[sets == s], dtype=np.float64)
        d = d[np.isfinite(d)]
        if len(d) >= MIN_PAIRS:
            shift = float(np.median(d))
            gain = GAIN_PER_MAD * float(np.median(np.abs(d - shift)))
            out[int(s)] = SetAlignment(shift, gain)
    return out


def place_scorer(
    row_fn: ScoreFn,
    places: Places,
    methods: Mapping[str, Method],
    sets: np.ndarray | None = None,
    pairs: np.ndarray | None = None,
) -> PlaceScorer:
    """Score places instead of rows: a place scores by its best experience, per method.

    Args:
        row_fn: ``row_fn(method_id, rows)`` -> raw scores of those rows (``None``: every
            row), e.g. :meth:`hmpf.index.reader.IndexReader.row_scorer`.
        places: the grouping.
        methods: method id -> instance (``higher_is_better`` picks max or min).
        sets: (N,) each row's experience set (:func:`experience_sets`); when given, each
            set's raw scores are first shifted to the originals' level for the query and a
            place's best lessened by its extra images' expected chance gain
            (:func:`align_pairs`), so neither the conditions an experience was taken in nor
            the number of a place's images lifts it.
        pairs: the rows a whole-database call aligns the sets on (default
            :func:`pair_sample` of ``sets``; a reader computes it once).

    Returns:
        a score function over places: tier 1 (``subset`` None) scores every row once and
        reduces per place (vectorised, ``reduceat`` over the rows grouped by place); a subset
        of places is expanded to their rows, scored and reduced. The reduction runs on the
        *raw* scores, so the hierarchy's normalisation sees one value per place, and a place
        with one experience scores exactly as that row.
    """
    return PlaceScorer(row_fn, places, methods, sets, pairs)


@dataclass(frozen=True)
class Experience:
    """One stored image of a place, described for an answer.

    Attributes:
        row: its row in the version.
        place: the place it belongs to.
        name: its name (``refs.names[row]``).
        original: the place's original reference (else an experience added from the fleet).
        log, vehicle, version: where a fleet experience came from: the log's id, the vehicle
            and the index version that answered the frame (None on an original reference or
            where not recorded).
        time: when the frame was taken, seconds since the epoch (None: not known).
        p_correct: the frame's ``p_correct`` when it was recorded (None: not known).
    """

    row: int
    place: int
    name: str
    original: bool
    log: str | None = None
    vehicle: str | None = None
    version: str | None = None
    time: float | None = None
    p_correct: float | None = None


def experience_of_row(refs: RefTable, places: Places, row: int) -> Experience:
    """Row ``row`` of ``refs`` as an :class:`Experience` (its provenance columns read where
    the version stores them; missing values as None)."""
    meta = refs.meta

    def text(col: str) -> str | None:
        v = meta.get(col)
        s = "" if v is None else str(v[row])
        return s or None

    def num(col: str) -> float | None:
        v = meta.get(col)
        x = float("nan") if v is None else float(v[row])
        return x if math.isfinite(x) else None

    original = row < places.n
    return Experience(
        row=int(row),
        place=int(places.place_of[row]),
        name=refs.names[row],
        original=original,
        log=None if original else text("exp_log"),
        vehicle=None if original else text("exp_vehicle"),
        version=None if original else text("exp_version"),
        time=None if original else num("exp_time"),
        p_correct=None if original else num("exp_p_correct"),
    )
