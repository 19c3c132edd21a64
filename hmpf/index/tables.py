"""Columnar, in-memory form of an index's contents (what is written to and read from HDF5).

* :class:`Ragged`: per-image arrays with a common trailing shape, concatenated along axis 0
  plus offsets (KAZE keypoints and descriptors; OLO's R x D regions are the equal-count case).
* A method's *columns*: an (N, D) matrix for a global method, ``{array name: Ragged}`` for a
  local one (the names are those of :meth:`~hmpf.methods.base.Method.to_arrays`).
* :class:`RefTable`: image names, content hashes and metadata columns.

Every operation keeps image order, so row ``i`` of every table is the same reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hmpf.index.layout import IndexBuildError
from hmpf.methods import Method

__all__ = [
    "EXPERIENCE_COLUMNS",
    "META_COLUMNS",
    "STORED_COLUMNS",
    "Columns",
    "Ragged",
    "RefTable",
    "columns_from_features",
    "concat_columns",
    "select_columns",
]

#: Optional metadata columns a user gives (besides the required ``name``); ``sequence`` is text.
META_COLUMNS = ("lat", "lon", "heading", "timestamp", "sequence")
#: Columns of a version holding fleet experiences (written by ``hmpf-index add --experiences``,
#: never read from a user's CSV). Rows ``0 .. P-1`` are the places' original references, in
#: place order, and every later row is an *experience* of one of them: ``place`` is NaN (or
#: absent) on an original reference and the index of its place on an experience. The others
#: say where an experience came from (its provenance): the log's id, the vehicle, when the
#: frame was taken (seconds since the epoch), its ``p_correct`` and the version that answered.
EXPERIENCE_COLUMNS = ("place", "exp_log", "exp_vehicle", "exp_version", "exp_time", "exp_p_correct")
#: Every metadata column a version may store.
STORED_COLUMNS = META_COLUMNS + EXPERIENCE_COLUMNS
TEXT_COLUMNS = frozenset({"sequence", "exp_log", "exp_vehicle", "exp_version"})


@dataclass(frozen=True)
class Ragged:
    """Per-image arrays ``(n_i, *item_shape)`` stored as one ``data`` block plus offsets.

    Attributes:
        data: (sum n_i, *item_shape) rows of every image, in image order.
        offsets: (N + 1,) int64; image ``i`` owns ``data[offsets[i]:offsets[i + 1]]``.
        scalar: the per-image arrays were 0-d (stored as one row each).
    """

    data: np.ndarray
    offsets: np.ndarray
    scalar: bool = False

    @classmethod
    def from_items(cls, items: Sequence[np.ndarray]) -> Ragged:
        arrays = [np.asarray(a) for a in items]
        scalar = bool(arrays) and all(a.ndim == 0 for a in arrays)
        if scalar:
            arrays = [a.reshape(1) for a in arrays]
        if any(a.ndim == 0 for a in arrays):
            raise IndexBuildError("a feature array is 0-d for some images and not for others")
        tails = {a.shape[1:] for a in arrays}
        dtypes = {a.dtype for a in arrays}
        if len(tails) > 1 or len(dtypes) > 1:
            raise IndexBuildError(
                f"per-image arrays differ in trailing shape or dtype: {sorted(map(str, tails))}, "
                f"{sorted(map(str, dtypes))}"
            )
        counts = np.array([a.shape[0] for a in arrays], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        data = np.concatenate(arrays) if arrays else np.zeros((0,), np.float32)
        return cls(data, offsets, scalar)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)

    def item(self, i: int) -> np.ndarray:
        a = self.data[self.offsets[i] : self.offsets[i + 1]]
        return a.reshape(()) if self.scalar else a

    def select(self, idx: np.ndarray) -> Ragged:
        """The images ``idx`` (in that order)."""
        idx = np.asarray(idx, dtype=np.int64)
        counts = self.counts[idx]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        rows = _ranges(self.offsets[idx], counts)
        return Ragged(self.data[rows], offsets, self.scalar)

    @staticmethod
    def concat(parts: Sequence[Ragged]) -> Ragged:
        parts = [p for p in parts if len(p) > 0] or list(parts[:1])
        base = np.concatenate([[0], np.cumsum([p.offsets[-1] for p in parts])])
        offsets = np.concatenate(
            [parts[0].offsets[:1]] + [p.offsets[1:] + b for p, b in zip(parts, base, strict=False)]
        )
        data = np.concatenate([p.data for p in parts])
        return Ragged(data, offsets.astype(np.int64), parts[0].scalar)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(s, s + c)`` for each (start, count), vectorised."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    ends = np.cumsum(counts)
    rep = np.repeat(starts - (ends - counts), counts)
    return np.arange(total, dtype=np.int64) + rep


#: One method's stored features: (N, D) matrix (global) or name -> Ragged (local).
Columns = np.ndarray | dict[str, Ragged]


def columns_from_features(method: Method, features: Sequence[Any]) -> Columns:
    """Per-image features -> columns via :meth:`Method.to_arrays`.

    Raises:
        IndexBuildError: a global method's feature is not one vector, or local arrays
            disagree in trailing shape or dtype across images.
    """
    if method.kind == "global":
        vecs = []
        for f in features:
            arrays = method.to_arrays(f)
            if len(arrays) != 1 or next(iter(arrays.values())).ndim != 1:
                raise IndexBuildError(
                    f"global method {method.name!r}: to_arrays must give one 1-d vector per "
                    f"image, got {{{', '.join(f'{k}: {v.shape}' for k, v in arrays.items())}}}"
                )
            vecs.append(next(iter(arrays.values())))
        if not vecs:
            return np.zeros((0, getattr(method, "dim", 0)), dtype=np.float32)
        return np.stack(vecs)
    per_key: dict[str, list[np.ndarray]] = {}
    for f in features:
        for k, v in method.to_arrays(f).items():
            per_key.setdefault(k, []).append(np.asarray(v))
    if features and any(len(v) != len(features) for v in per_key.values()):
        raise IndexBuildError(f"method {method.name!r}: to_arrays gives different keys per image")
    return {k: Ragged.from_items(v) for k, v in per_key.items()}


def select_columns(cols: Columns, idx: np.ndarray) -> Columns:
    if isinstance(cols, np.ndarray):
        return cols[np.asarray(idx, dtype=np.int64)]
    return {k: r.select(idx) for k, r in cols.items()}


def concat_columns(a: Columns, b: Columns) -> Columns:
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
        if a.shape[1:] != b.shape[1:] or a.dtype != b.dtype:
            raise IndexBuildError(
                f"new features {b.shape[1:]} {b.dtype} do not match the index's "
                f"{a.shape[1:]} {a.dtype}; rebuild instead of add"
            )
        return np.concatenate([a, b])
    assert isinstance(a, dict) and isinstance(b, dict)
    if set(a) != set(b):
        raise IndexBuildError("new features have different arrays than the index; rebuild")
    return {k: Ragged.concat([a[k], b[k]]) for k in a}


@dataclass
class RefTable:
    """Names, sha256 of the image bytes and metadata columns of the references, in order.

    ``meta`` holds only the columns that were given: float64 arrays (NaN = missing) for
    lat / lon / heading / timestamp (seconds since the epoch), object arrays of str for
    ``sequence``.
    """

    names: list[str]
    sha256: list[str]
    meta: dict[str, np.ndarray] = field(default_factory=dict)
    sources: list[str] = field(default_factory=list)  # folder each image was read from

    def __post_init__(self) -> None:
        if not self.sources:
            self.sources = [""] * len(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def select(self, idx: np.ndarray) -> RefTable:
        idx = np.asarray(idx, dtype=np.int64)
        return RefTable(
            [self.names[i] for i in idx],
            [self.sha256[i] for i in idx],
            {k: v[idx] for k, v in self.meta.items()},
            [self.sources[i] for i in idx],
        )

    def concat(self, other: RefTable) -> RefTable:
        keys = set(self.meta) | set(other.meta)
        meta = {k: np.concatenate([_column(self, k), _column(other, k)]) for k in keys}
        return RefTable(
            self.names + other.names,
            self.sha256 + other.sha256,
            meta,
            self.sources + other.sources,
        )


def _column(t: RefTable, key: str) -> np.ndarray:
    if key in t.meta:
        return t.meta[key]
    if key in TEXT_COLUMNS:
        return np.array([""] * len(t), dtype=object)
    return np.full(len(t), np.nan)
