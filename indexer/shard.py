"""``hmpf-index shard``: split an index version into region shards (:mod:`hmpf.shards`).

    hmpf-index shard --index maps/city --shards 4 --overlap 20 --out maps/city-shards
    hmpf-index shard --index maps/city --shards 4 --overlap 20 --by position --out ...

writes, in ``--out``::

    shards.json          the map: places, per shard its places (global ids) and owned ones
    map/references.h5    the whole map's reference table (names, positions, routes; no
                         descriptors) for the router
    map/profile.h5       the whole map's reference profile (what the router's confidence
                         features compare with)
    shard-00/ ...        one index folder per shard: a published version (CURRENT) of its
                         places, written as ``hmpf-index remove`` writes one (the parent's
                         rows, fitted state, models, storage options), served by
                         ``hmpf-serve shards`` (or ``hmpf-serve --index`` on its own)

The stretches follow the routes (``--by route``, the default: the version's route order,
``sequence`` then ``timestamp``) or the places' positions (``--by position``: a curve through
the ``lat``/``lon`` of the places, so each shard is a compact region; places without a
position go to the last shard); ``--overlap`` places on either side of a border are in both
neighbours.
Running it again into the same ``--out`` publishes a new version in every shard folder.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.index import layout
from hmpf.index.places import augments
from hmpf.index.reader import IndexReader
from hmpf.index.storage import write_profile, write_references
from hmpf.index.tables import select_columns
from hmpf.shards import MAP_DIR, MAP_FILE, ShardError, ShardMap, plan, position_order
from indexer.build import (
    NewVersion,
    Summary,
    VersionTransaction,
    _parent,
    _parent_options,
    _row_thumbnails,
)

__all__ = ["SPLITS", "ShardSummary", "split"]

#: How :func:`split` orders the places before cutting them into stretches.
SPLITS = ("route", "position")


@dataclass
class ShardSummary:
    """What a split wrote."""

    out: Path
    source: str
    places: int
    shards: list[Summary]
    covered: list[int]
    owned: list[int]

    def lines(self) -> list[str]:
        out = [
            f"split {self.source} ({self.places} places) into {len(self.shards)} shards "
            f"in {self.out}:"
        ]
        for i, s in enumerate(self.shards):
            out.append(
                f"  shard-{i:02d} {s.version}: {self.covered[i]} places "
                f"({self.owned[i]} owned, {self.covered[i] - self.owned[i]} in the overlap), "
                f"{s.bytes_total / 1e6:.1f} MB, {s.seconds:.1f} s"
            )
        out.append(f"serve them with: hmpf-serve shards --shards {self.out}")
        return out


def _refuse(parent: IndexReader) -> None:
    """What a shard cannot answer exactly is refused before anything is written."""
    if parent.has_experiences:
        raise ShardError(
            f"{parent.path}: a version with fleet experiences cannot be split yet; split the "
            "version before `hmpf-index add --experiences`, or remove the experiences"
        )
    dba = [m for m, x in parent.methods.items() if x.kind == "global" and augments(x)]
    if dba:
        raise ShardError(
            f"{parent.path}: methods {dba} average neighbours along the route (dba): a "
            "shard's border places would score differently from the whole map's"
        )


def split(
    index: str | Path, shards: int, overlap: int, out: str | Path, by: str = "route"
) -> ShardSummary:
    """Split the current version of ``index`` into ``shards`` region shards in ``out``,
    along the routes or the positions (``by``, one of :data:`SPLITS`).

    Raises:
        ShardError: a bad number of shards or overlap, a version that cannot be split (or,
            ``by="position"``, has no positions).
        IndexCorruptError: the version does not verify (nothing is written).
    """
    out = Path(out)
    if by not in SPLITS:
        raise ShardError(f"split by {by!r}: one of {', '.join(SPLITS)}")
    if out.resolve() == Path(index).resolve():
        raise ShardError("--out must be another folder than --index")
    with _parent(Path(index), "shard") as parent:
        _refuse(parent)
        n = parent.n
        plans = plan(_order(parent, by), shards, overlap)
        shard_map = ShardMap.from_plans(n, plans)
        out.mkdir(parents=True, exist_ok=True)
        options = _parent_options(parent, None)
        cols = {mid: parent.columns(mid) for mid in parent.methods}
        thumbs = None if parent.thumbnails is None else _row_thumbnails(parent)
        summaries = []
        for s, p in enumerate(plans):
            tx = VersionTransaction(out / shard_map.names[s], "shard")
            with tx:
                tx.begin(
                    {
                        "operation": "shard",
                        "parent": str(parent.path),
                        "places": len(p.covered),
                        "first": int(p.covered[0]),
                    }
                )
                new = NewVersion(
                    parent.config,
                    parent.methods,
                    parent.refs.select(p.covered),
                    {mid: select_columns(c, p.covered) for mid, c in cols.items()},
                    options,
                    parent,
                    retrain=False,
                    thumbnails=None if thumbs is None else thumbs.select(p.covered),
                )
                summaries.append(tx.publish(new, extracted=0))
        _write_map(out, parent, shard_map, [s.version for s in summaries], by)
        return ShardSummary(
            out,
            f"{parent.root}@{parent.version}",
            n,
            summaries,
            [len(p.covered) for p in plans],
            [len(p.owned) for p in plans],
        )


def _order(parent: IndexReader, by: str) -> np.ndarray:
    """The places in the order the stretches are cut from."""
    if by == "route":
        return parent.route_map().ordered
    meta, n = parent.refs.meta, parent.n
    lat, lon = meta.get("lat"), meta.get("lon")
    if lat is None or lon is None or not np.isfinite(lat[:n] + lon[:n]).any():
        raise ShardError(f"{parent.path}: no place has a position (lat, lon): split it --by route")
    return position_order(lat[:n], lon[:n])


def _sketch_entry(parent: IndexReader) -> dict[str, Any] | None:
    """The parent's :meth:`~hmpf.index.reader.IndexReader.motion_sketch` as the shard map
    stores it: the method, the descriptors' dimension (the projection is seeded by it) and
    the map's step; None when its filter weighs no motion."""
    made = parent.motion_sketch()
    if made is None:
        return None
    mid, sketch = made
    return {"method": mid, "dim": int(sketch.projection.shape[1]), "step": sketch.step}


def _write_map(
    out: Path, parent: IndexReader, shard_map: ShardMap, versions: list[str], by: str
) -> None:
    """The router's files: the whole map's reference table and profile, then (last, by an
    atomic rename) ``shards.json``."""
    folder = out / MAP_DIR
    folder.mkdir(exist_ok=True)
    write_references(folder / layout.REFERENCES_H5, parent.refs, {}, {}, "exact")
    profile = parent.reference_profile()
    write_profile(folder / layout.PROFILE_H5, profile, {"source": parent.version})
    extra: dict[str, Any] = {
        "source": {"index": str(parent.root), "version": parent.version},
        "written": versions,
        "config_digest": parent.config.digest(),
        "by": by,
        "profile": layout.PROFILE_H5,
        # the source version's map prior, which every answer's features carry
        "map_prior": parent.map_prior(),
        # the source version's sketch of the frames' motion (a filter that weighs it): the
        # router sketches each query frame as the unsharded version does
        "motion_sketch": _sketch_entry(parent),
    }
    data = shard_map.to_json(extra)
    tmp = out / f".{MAP_FILE}.tmp"
    tmp.write_text(json.dumps(data))
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, out / MAP_FILE)
    layout.fsync_dir(out)
