"""The router's view of a sharded map: one reader over every shard (:mod:`hmpf.shards`).

:class:`ShardedReader` answers what the service asks of an
:class:`~hmpf.index.reader.IndexReader` (the reference table, the route map, the profile,
the hierarchy, query extraction, a scorer) for the whole map, while the descriptors stay in
the shards: its :meth:`ShardedReader.scorer` scatters scores to them through a
:class:`ShardBackend`. Two backends: :class:`LocalShards` (every shard opened in this process:
tests, a split checked on one machine) and the Ray Serve deployments of
:mod:`service.shards`. The shard side of a request is :func:`score_request`, the same code in
both.

The router extracts a query's features once, with the methods (and their stored models) of
one shard version: every shard of a split stores the same fitted methods, so the features are
those the unsharded version extracts.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from concurrent.futures import Executor
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from hmpf.confidence import ReferenceProfile, stored_map_prior
from hmpf.config import HierarchyConfig
from hmpf.hierarchy import Hierarchy, ScoreFn
from hmpf.index import layout
from hmpf.index.places import Experience, Places, experience_of_row, route_map_of
from hmpf.index.reader import IndexReader
from hmpf.index.storage import open_h5, read_profile, read_ref_table
from hmpf.index.tables import RefTable
from hmpf.methods import Method
from hmpf.sequence import MotionSketch, RouteMap
from hmpf.shards import MAP_DIR, ShardedScorer, ShardError, ShardScores, read_shard_map

__all__ = [
    "LocalShards",
    "ShardBackend",
    "ShardedReader",
    "describe_shard",
    "score_request",
]

Requests = Sequence[tuple[str, np.ndarray | None]]


# -- the shard side ----------------------------------------------------------------------------
def score_request(
    reader: IndexReader, features: Mapping[str, Any], requests: Requests
) -> ShardScores:
    """One shard's raw scores for one query: per request (method id, local place ids or None
    for all), exactly what the shard's :meth:`~hmpf.index.reader.IndexReader.row_scorer`
    gives (so an exact method's subset is the same numbers as its whole-shard scores there).

    Raises:
        ShardError: an unknown method, or local ids outside the shard.
    """
    fn = reader.row_scorer(features)
    out = []
    for mid, ids in requests:
        if mid not in reader.methods or mid not in features:
            raise ShardError(f"shard {reader.root.name}: no method {mid!r} (or no feature of it)")
        if ids is not None:
            ids = np.asarray(ids, dtype=np.int64)
            if len(ids) and (ids.min() < 0 or ids.max() >= reader.n):
                raise ShardError(f"shard {reader.root.name}: place ids outside 0 .. {reader.n - 1}")
        out.append(np.asarray(fn(mid, ids)))
    return ShardScores(reader.version, out)


def describe_shard(reader: IndexReader) -> dict[str, Any]:
    """What the router checks a shard by: its version, places' names, config digest."""
    return {
        "version": reader.version,
        "names": list(reader.place_names),
        "config_digest": reader.config.digest(),
        "thumbnails": reader.thumbnails is not None,
    }


# -- backends ------------------------------------------------------------------------------------
class ShardBackend(Protocol):
    """How the router reaches its shards (index ``s`` in the :class:`~hmpf.shards.ShardMap`)."""

    def describe(self, s: int) -> dict[str, Any]: ...

    def scatter(
        self, features: Mapping[str, Any], calls: Sequence[tuple[int, Requests]]
    ) -> list[ShardScores]: ...

    def local_features(self, s: int, mid: str, local: np.ndarray) -> list[Any]: ...

    def thumbnail(self, s: int, local: int) -> bytes | None: ...

    def close(self) -> None: ...


class LocalShards:
    """Every shard of ``folder`` opened in this process (their ``CURRENT`` versions, or the
    versions named in ``versions``)."""

    def __init__(self, folder: str | Path, versions: Sequence[str | None] | None = None) -> None:
        self.folder = Path(folder)
        shard_map, _ = read_shard_map(self.folder)
        self.readers: list[IndexReader] = []
        try:
            for s, name in enumerate(shard_map.names):
                v = None if versions is None else versions[s]
                self.readers.append(IndexReader(self.folder / name, v, verify="stamp"))
        except BaseException:
            self.close()
            raise
        #: shard indices each scatter asked (tests: which shards a query reached)
        self.calls: list[list[int]] = []

    def describe(self, s: int) -> dict[str, Any]:
        return describe_shard(self.readers[s])

    def scatter(
        self, features: Mapping[str, Any], calls: Sequence[tuple[int, Requests]]
    ) -> list[ShardScores]:
        self.calls.append([s for s, _ in calls])
        return [score_request(self.readers[s], features, req) for s, req in calls]

    def local_features(self, s: int, mid: str, local: np.ndarray) -> list[Any]:
        return self.readers[s].local_features(mid, local)

    def thumbnail(self, s: int, local: int) -> bytes | None:
        return self.readers[s].thumbnail(local)

    def close(self) -> None:
        for r in self.readers:
            r.close()
        self.readers.clear()


# -- the router's reader -------------------------------------------------------------------------
class _Thumbnails:
    """Stands for "the map has thumbnails" (:attr:`ShardedReader.thumbnails`)."""


class ShardedReader:
    """The whole sharded map, read as one index version (see the module's docstring).

    Args:
        folder: the shard folder (``hmpf-index shard --out``).
        backend: how to reach the shards.
        extractor: a reader of one shard version, for the methods, the models and the config
            (the router's query extraction); closed with this reader.
    """

    def __init__(self, folder: str | Path, backend: ShardBackend, extractor: IndexReader) -> None:
        self.folder = Path(folder)
        self.root = self.folder
        self.path = self.folder
        self.backend = backend
        self.extractor = extractor
        self.map, self.info = read_shard_map(self.folder)
        with open_h5(self.folder / MAP_DIR / layout.REFERENCES_H5) as f:
            self.refs: RefTable = read_ref_table(f)
        if len(self.refs) != self.map.n:
            raise ShardError(
                f"{self.folder}: the map table holds {len(self.refs)} places, "
                f"{self.map.n} in the shard map"
            )
        self.config: HierarchyConfig = extractor.config
        if self.info.get("config_digest") != self.config.digest():
            raise ShardError(f"{self.folder}: the shards hold another config than the map")
        self.methods: dict[str, Method] = extractor.methods
        self.n = self.n_rows = self.map.n
        self.places = Places.identity(self.n)
        self.has_experiences = False
        self.verified_by: str | None = "full"
        self.verify_seconds: float | None = None
        described = [backend.describe(s) for s in range(self.map.shards)]
        for s, d in enumerate(described):
            want = [self.refs.names[i] for i in self.map.covered[s]]
            if d["names"] != want:
                raise ShardError(
                    f"{self.folder}: {self.map.names[s]} version {d['version']} holds other "
                    "places than the shard map says; split again or use its matching version"
                )
            if d["config_digest"] != self.config.digest():
                raise ShardError(f"{self.map.names[s]} holds another config than the map")
        #: per shard, the version loaded
        self.versions = [str(d["version"]) for d in described]
        self.version = "+".join(
            f"{name}@{v}" for name, v in zip(self.map.names, self.versions, strict=True)
        )
        self.thumbnails = _Thumbnails() if all(d["thumbnails"] for d in described) else None
        self.manifest: dict[str, Any] = {
            **extractor.manifest,
            "version": self.version,
            "shards": {
                "folder": self.folder.name,
                "versions": self.versions,
                "map": hashlib.sha256(json.dumps(self.info, sort_keys=True).encode()).hexdigest(),
            },
        }
        self.manifest.pop("files", None)
        self._routes: RouteMap | None = None
        self._profile: ReferenceProfile | None = None

    # -- what the service reads --------------------------------------------------------------
    @property
    def place_names(self) -> list[str]:
        return self.refs.names

    def hierarchy(self) -> Hierarchy:
        return Hierarchy(self.config, self.methods)

    def route_map(self) -> RouteMap:
        """The whole map's routes (what the unsharded version builds from the same table)."""
        if self._routes is None:
            self._routes = route_map_of(self.refs.meta, self.n, self.config)
        return self._routes

    def reference_profile(self) -> ReferenceProfile:
        """The whole map's reference profile, as the split stored it, with the source
        version's map prior (:meth:`map_prior`)."""
        if self._profile is None:
            profile = read_profile(self.folder / MAP_DIR / layout.PROFILE_H5)
            if profile.n != self.n:
                raise ShardError(f"{self.folder}: a profile of {profile.n} places for {self.n}")
            self._profile = dataclasses.replace(profile, map_prior=self.map_prior())
        return self._profile

    def map_prior(self) -> float | None:
        """The map prior of the version the map was split from (None: it stored none, or
        the map was split before splits kept it)."""
        try:
            return stored_map_prior(self.info.get("map_prior"))
        except ValueError as exc:
            raise ShardError(f"{self.folder}: {exc}") from None

    def motion_sketch(self) -> tuple[str, MotionSketch] | None:
        """``(method id, sketch)`` of the frames' motion for a config whose filter weighs it,
        as the source version made it (the split stores its step): the router sketches each
        frame from the query's own descriptor, as the unsharded version does. None when the
        filter weighs no motion, or the version could not make a sketch either.

        Raises:
            ShardError: the filter weighs motion and the map was split before splits kept
                the sketch, or the stored sketch is unusable.
        """
        if not self.config.sequence_params().motion:
            return None
        if "motion_sketch" not in self.info:
            raise ShardError(
                f"{self.folder}: the sequence filter weighs motion (sequence.stop_factor or "
                "slow_factor) and "
                "this split holds no motion sketch; split the version again"
            )
        entry = self.info["motion_sketch"]
        if entry is None:  # the version gave none either (no consecutive places)
            return None
        if not isinstance(entry, dict):
            raise ShardError(f"{self.folder}: an unreadable motion sketch {entry!r}")
        try:
            mid, dim, step = str(entry["method"]), int(entry["dim"]), float(entry["step"])
        except (KeyError, TypeError, ValueError):
            raise ShardError(f"{self.folder}: an unreadable motion sketch {entry!r}") from None
        if mid not in self.methods or dim < 1 or not (math.isfinite(step) and step > 0):
            raise ShardError(f"{self.folder}: an unusable motion sketch {entry!r}")
        return mid, MotionSketch(MotionSketch.projection_for(dim), step)

    def extract_query(
        self,
        image: np.ndarray,
        ms: dict[str, float] | None = None,
        executor: Executor | None = None,
    ) -> dict[str, Any]:
        return self.extractor.extract_query(image, ms, executor)

    def scorer(self, query: Mapping[str, Any]) -> ShardedScorer:
        tier1 = list(self.config.tiers[0].methods)
        exact = {m: self.extractor.is_exact(m) for m in self.methods}
        return ShardedScorer(
            self.map,
            query,
            lambda calls: self.backend.scatter(query, calls),
            tier1,
            exact,
            self.versions,
        )

    def matched_rows(self, score_fn: ScoreFn) -> np.ndarray | None:
        return None  # every place is one image (a split refuses experiences)

    def experience(self, row: int) -> Experience:
        if not 0 <= row < self.n:
            raise IndexError(f"row {row} out of range 0 .. {self.n - 1}")
        return experience_of_row(self.refs, self.places, row)

    def _at_owner(self, place: int) -> tuple[int, int]:
        routes = self.map.route(np.array([place], dtype=np.int64))
        ((s, (_, local)),) = routes.items()
        return s, int(local[0])

    def local_features(self, mid: str, idx: np.ndarray) -> list[Any]:
        out = []
        for i in np.asarray(idx, dtype=np.int64).tolist():
            s, local = self._at_owner(int(i))
            out.extend(self.backend.local_features(s, mid, np.array([local], dtype=np.int64)))
        return out

    def thumbnail(self, i: int) -> bytes | None:
        if self.thumbnails is None or not 0 <= i < self.n:
            return None
        s, local = self._at_owner(int(i))
        return self.backend.thumbnail(s, local)

    def is_exact(self, mid: str) -> bool:
        return self.extractor.is_exact(mid)

    def close(self) -> None:
        self.extractor.close()
        self.backend.close()

    def __len__(self) -> int:
        return self.n

    @classmethod
    def open_local(cls, folder: str | Path) -> ShardedReader:
        """Every shard of ``folder`` opened in this process (:class:`LocalShards`)."""
        backend = LocalShards(folder)
        try:
            extractor = IndexReader(Path(folder) / backend.readers[0].root.name, verify="stamp")
            return cls(folder, backend, extractor)
        except BaseException:
            backend.close()
            raise
