"""Region shards: one map split into parts along its routes, queried as if it were whole.

A map too large for one machine is split into ``n`` *shards* (:func:`plan`): contiguous
stretches of its routes (the places in :class:`~hmpf.sequence.RouteMap` order, route after
route, each in driving order), or of a curve through their positions
(:func:`position_order`: each shard a compact region), each widened by ``overlap`` places on
either side, so that a place near a border is held by both neighbours. Every place is
*owned* by exactly one shard (the stretch before widening): only the owner's score for it is
ever used, so a place in an overlap never counts twice. Each shard is an ordinary index
version of its places (``hmpf-index shard``, :mod:`indexer.shard`), its places in ascending
global id order; the map itself (every place's name and metadata, the whole map's reference
profile) is written beside the shards for the router.

*Scatter / gather* (:class:`ShardedScorer`). The hierarchy (:class:`~hmpf.hierarchy.Hierarchy`)
runs once, at the router, over the whole map's place ids; only its ``score_fn`` is
distributed. Tier 1 of the whole map is scattered to every shard, each returns its raw scores,
and the router gathers the owners' scores into the whole map's raw vector; a subset (a later
tier's candidates, or tier 1 under a GPS prior) is sent only to the shards that own its places
(or to one shard holding all of them, overlap included), so a GPS prior reaches only the shards
covering it. Every raw score is the very number the unsharded index computes for that place
(the same stored descriptor, the same method), so normalisation over the whole map, the
fusion, every confidence feature (tier-1 rank, margin and z over the whole map, rivals more
than a window along the route, the reference profile's z), ``p_correct``, the sequence
filter's evidence: all are computed by the unchanged code on the same numbers, and the answer
is bit for bit the unsharded one. Why raw vectors rather than per-shard aggregates (min, max,
sums): ``tier1_z`` is a mean and standard deviation over the whole map, and numpy's pairwise
summation over one array cannot be reproduced bit for bit from per-shard partial sums.

Exact only where each shard's raw score of a place equals the unsharded one: exact (Flat)
tier-1 types (an approximate FAISS type searches each shard's index on its own), methods that
score a place from its own descriptor (no ``dba`` route augmentation, which averages
neighbours along the route), and versions without fleet experiences (refused by the split).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.errors import HmpfError

__all__ = [
    "MAP_DIR",
    "MAP_FILE",
    "ShardChanged",
    "ShardError",
    "ShardUnavailable",
    "ShardMap",
    "ShardPlan",
    "ShardScores",
    "ShardedScorer",
    "plan",
    "position_order",
    "read_shard_map",
    "shard_name",
]

#: The map's description in a shard folder (JSON), and the folder of the whole map's tables.
MAP_FILE = "shards.json"
MAP_DIR = "map"
#: ``format`` / ``version`` of :data:`MAP_FILE`.
FORMAT, FORMAT_VERSION = "hmpf-shards", 1


class ShardError(HmpfError):
    """A shard folder that cannot be used, or a shard that does not answer as the map says."""


class ShardUnavailable(Exception):
    """A shard could not answer a query (no replica left, or another version): a passing
    state, not a bad request (the service answers 503; not an :class:`HmpfError`, which a
    query answers as a bad image)."""

    code = "shard_unavailable"


class ShardChanged(ShardUnavailable):
    """A shard answered from another version than the router loaded the map from."""

    code = "shard_changed"


def shard_name(i: int) -> str:
    """The index folder of shard ``i`` inside a shard folder."""
    return f"shard-{i:02d}"


@dataclass(frozen=True)
class ShardPlan:
    """One shard of a split: the places it holds and those it answers for (global ids,
    ascending; ``owned`` is a subset of ``covered``)."""

    covered: np.ndarray
    owned: np.ndarray


def plan(ordered: np.ndarray, n_shards: int, overlap: int) -> list[ShardPlan]:
    """Split places, in route order (``ordered``: every place id once), into ``n_shards``
    contiguous stretches of nearly equal length (the owners), each widened by ``overlap``
    places before and after along the same order (the covered places).

    Raises:
        ShardError: ``n_shards`` < 1 or more than the places, ``overlap`` < 0.
    """
    order = np.asarray(ordered, dtype=np.int64)
    n = len(order)
    if n_shards < 1:
        raise ShardError("the number of shards must be at least 1")
    if n_shards > n:
        raise ShardError(f"{n_shards} shards for {n} places: at most one shard per place")
    if overlap < 0:
        raise ShardError("the overlap must be >= 0 places")
    if len(np.unique(order)) != n:
        raise ShardError("the route order must hold every place once")
    bounds = np.linspace(0, n, n_shards + 1).round().astype(np.int64)
    out = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        wide = order[max(0, lo - overlap) : min(n, hi + overlap)]
        out.append(ShardPlan(np.sort(wide), np.sort(order[lo:hi])))
    return out


#: Bits per axis of :func:`position_order`'s curve (a cell of about 1/65536 of the map's side).
CURVE_BITS = 16


def position_order(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Place ids along a Hilbert curve over their positions: consecutive places on the curve
    are near each other, so a stretch of it (a shard of :func:`plan`) is a compact region,
    whatever the routes. Places without a position come last, in id order.

    Positions are scaled alike on both axes (longitude by the cosine of the mean latitude),
    over the square around every position.
    """
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    ok = np.isfinite(lat) & np.isfinite(lon)
    ids = np.flatnonzero(ok)
    rest = np.flatnonzero(~ok)
    if len(ids) == 0:
        return rest.astype(np.int64)
    y = lat[ids]
    x = lon[ids] * np.cos(np.radians(float(np.mean(y))))
    side = max(float(np.ptp(x)), float(np.ptp(y)), 1e-12)
    top = (1 << CURVE_BITS) - 1
    xi = np.minimum((x - x.min()) / side * top, top).astype(np.int64)
    yi = np.minimum((y - y.min()) / side * top, top).astype(np.int64)
    d = _hilbert(xi, yi, CURVE_BITS)
    return np.concatenate([ids[np.lexsort((ids, d))], rest]).astype(np.int64)


def _hilbert(x: np.ndarray, y: np.ndarray, bits: int) -> np.ndarray:
    """Distance along the Hilbert curve of order ``bits`` of the cells (x, y) (integers in
    ``[0, 2**bits)``), the classic ``xy2d``, vectorised."""
    x, y = x.copy(), y.copy()
    n = 1 << bits
    d = np.zeros(len(x), dtype=np.int64)
    s = n >> 1
    while s > 0:
        rx = (x & s) > 0
        ry = (y & s) > 0
        d += s * s * ((3 * rx.astype(np.int64)) ^ ry.astype(np.int64))
        flip = ~ry & rx
        x[flip], y[flip] = n - 1 - x[flip], n - 1 - y[flip]
        swap = ~ry
        x[swap], y[swap] = y[swap], x[swap].copy()
        s >>= 1
    return d


def _digest(ids: np.ndarray) -> str:
    return hashlib.sha256(np.asarray(ids, dtype="<i8").tobytes()).hexdigest()[:16]


@dataclass
class ShardMap:
    """Which shard holds and owns which place.

    Attributes:
        n: places of the whole map.
        names: each shard's index folder (relative to the shard folder).
        covered: per shard, its places (global ids, ascending: its local id ``j`` is
            ``covered[j]``).
        owner: (n,) the shard that answers for each place.
    """

    n: int
    names: list[str]
    covered: list[np.ndarray]
    owner: np.ndarray
    _local: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.owner = np.asarray(self.owner, dtype=np.int64)
        if self.owner.shape != (self.n,) or (self.owner < 0).any():
            raise ShardError("every place must have an owning shard")
        if self.owner.max(initial=-1) >= len(self.names) or len(self.covered) != len(self.names):
            raise ShardError("an owner names no shard")
        # (n,) each place's local id in its owner
        self._local = np.full(self.n, -1, dtype=np.int64)
        for s, cov in enumerate(self.covered):
            mine = np.flatnonzero(self.owner[cov] == s)
            self._local[cov[mine]] = mine
        if (self._local < 0).any():
            raise ShardError("a place is owned by a shard that does not hold it")

    @classmethod
    def from_plans(cls, n: int, plans: Sequence[ShardPlan]) -> ShardMap:
        owner = np.full(n, -1, dtype=np.int64)
        for s, p in enumerate(plans):
            if (owner[p.owned] >= 0).any():
                raise ShardError("a place is owned by two shards")
            owner[p.owned] = s
        return cls(n, [shard_name(s) for s in range(len(plans))], [p.covered for p in plans], owner)

    @property
    def shards(self) -> int:
        return len(self.names)

    def owned(self, s: int) -> tuple[np.ndarray, np.ndarray]:
        """Shard ``s``'s owned places: (local ids in the shard, global ids)."""
        cov = self.covered[s]
        mine = np.flatnonzero(self.owner[cov] == s)
        return mine, cov[mine]

    def route(self, ids: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Where to score the places ``ids`` (global): per shard, (positions in ``ids``, local
        ids there). One shard when one holds them all (the one owning most of them, overlap
        included), else each place at its owner."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return {}
        owners = self.owner[ids]
        counts = np.bincount(owners, minlength=self.shards)
        most = int(np.argmax(counts))  # the only shard that can hold them all, if one does
        cov = self.covered[most]
        pos = np.minimum(np.searchsorted(cov, ids), len(cov) - 1)
        if (cov[pos] == ids).all():
            return {most: (np.arange(len(ids)), pos)}
        out = {}
        for s in np.flatnonzero(counts):
            at = np.flatnonzero(owners == s)
            out[int(s)] = (at, self._local[ids[at]])
        return out

    # -- stored -----------------------------------------------------------------------------
    def to_json(self, extra: Mapping[str, Any]) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "places": self.n,
            "shards": [
                {
                    "name": name,
                    "covered": self.covered[s].tolist(),
                    "owned": self.owned(s)[1].tolist(),
                    "digest": _digest(self.covered[s]),
                }
                for s, name in enumerate(self.names)
            ],
            **extra,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], where: str) -> ShardMap:
        try:
            if data.get("format") != FORMAT or data.get("version") != FORMAT_VERSION:
                raise ShardError(
                    f"{where}: not a shard map this hmpf reads (format {data.get('format')!r}, "
                    f"version {data.get('version')!r})"
                )
            n = int(data["places"])
            names, covered = [], []
            owner = np.full(n, -1, dtype=np.int64)
            for s, entry in enumerate(data["shards"]):
                names.append(str(entry["name"]))
                covered.append(np.asarray(entry["covered"], dtype=np.int64))
                owner[np.asarray(entry["owned"], dtype=np.int64)] = s
            return cls(n, names, covered, owner)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ShardError(f"{where}: damaged shard map ({exc})") from None


def read_shard_map(folder: Path) -> tuple[ShardMap, dict[str, Any]]:
    """The :class:`ShardMap` a shard folder describes, and its whole JSON."""
    path = Path(folder) / MAP_FILE
    if not path.is_file():
        raise ShardError(f"{folder}: no {MAP_FILE}; split an index with `hmpf-index shard`")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ShardError(f"{path}: unreadable ({exc})") from None
    if not isinstance(data, dict):
        raise ShardError(f"{path}: not a shard map")
    return ShardMap.from_json(data, str(path)), data


# -- scatter / gather ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ShardScores:
    """One shard's answer to a score request: the version that computed it and, per request,
    the raw scores (the whole shard's for a ``None`` subset, else at the asked local ids)."""

    version: str
    scores: list[np.ndarray]


#: ``scatter(calls)``: run ``(shard, requests)`` calls, possibly at once; results in order.
Scatter = Callable[
    [Sequence[tuple[int, Sequence[tuple[str, np.ndarray | None]]]]], list[ShardScores]
]


class ShardedScorer:
    """A :data:`~hmpf.hierarchy.ScoreFn` over the whole map's place ids, scored at the shards.

    Mirrors :meth:`hmpf.index.reader.IndexReader.row_scorer`: the whole map's scores of a
    method are asked once (every tier-1 method of the config in the same request to each
    shard) and remembered; a later tier's subset of a remembered exact method is gathered
    from them, any other subset is scored where :meth:`ShardMap.route` sends it.

    Args:
        shard_map: the map.
        features: the query's features (method id -> feature).
        scatter: sends requests to shards and returns their answers in order.
        tier1: the methods scored over the whole map together (the first tier's).
        exact: method id -> whether the whole-map scores of it are exact (a subset may be
            gathered from them).
        versions: per shard, the version the map was loaded from: an answer from another
            version is refused (:class:`ShardError`).
    """

    def __init__(
        self,
        shard_map: ShardMap,
        features: Mapping[str, Any],
        scatter: Scatter,
        tier1: Sequence[str],
        exact: Mapping[str, bool],
        versions: Sequence[str] | None = None,
    ) -> None:
        self.map = shard_map
        self.features = features
        self.scatter = scatter
        self.tier1 = list(tier1)
        self.exact = dict(exact)
        self.versions = list(versions) if versions is not None else None
        self.memo: dict[str, np.ndarray] = {}
        #: shards asked, per request (for tests and metrics): lists of shard indices
        self.asked: list[list[int]] = []

    def _check(self, s: int, got: ShardScores) -> None:
        if self.versions is not None and got.version != self.versions[s]:
            raise ShardChanged(
                f"shard {self.map.names[s]} answered from version {got.version}, the map was "
                f"loaded from {self.versions[s]}; the router reloads it, try again"
            )

    def _whole(self, mid: str) -> np.ndarray:
        mids = [mid] + [m for m in self.tier1 if m != mid and m not in self.memo]
        calls = [(s, [(m, None) for m in mids]) for s in range(self.map.shards)]
        self.asked.append([s for s, _ in calls])
        answers = self.scatter(calls)
        out: dict[str, np.ndarray] = {}
        for (s, _), got in zip(calls, answers, strict=True):
            self._check(s, got)
            local, ids = self.map.owned(s)
            for m, raw in zip(mids, got.scores, strict=True):
                raw = np.asarray(raw)
                if m not in out:
                    out[m] = np.empty(self.map.n, dtype=raw.dtype)
                out[m][ids] = raw[local]
        self.memo.update(out)
        return self.memo[mid]

    def _subset(self, mid: str, subset: np.ndarray) -> np.ndarray:
        routes = self.map.route(subset)
        calls = [(s, [(mid, local)]) for s, (_, local) in routes.items()]
        self.asked.append([s for s, _ in calls])
        answers = self.scatter(calls) if calls else []
        out: np.ndarray | None = None
        for (s, _), got in zip(calls, answers, strict=True):
            self._check(s, got)
            raw = np.asarray(got.scores[0])
            if out is None:
                out = np.empty(len(subset), dtype=raw.dtype)
            out[routes[s][0]] = raw
        return np.zeros(0) if out is None else out

    def __call__(self, mid: str, subset: np.ndarray | None) -> np.ndarray:
        if subset is None:
            return self.memo[mid] if mid in self.memo else self._whole(mid)
        subset = np.asarray(subset, dtype=np.int64)
        if mid in self.memo and self.exact.get(mid, False):
            return self.memo[mid][subset]
        return self._subset(mid, subset)
