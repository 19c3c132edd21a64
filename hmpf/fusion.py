"""Fusion maths as small pure functions (spec §5, docs/spec/fusion.md).

Shapes: ``N`` is the database size, ``F`` the number of candidates entering the final tier.
All scores produced here follow one convention: **higher is better, best = 1, worst = 0**.
Off-candidate entries of a full-length (N,) score vector are ``0`` in faithful mode (the
original's zero scatter) and ``NaN`` in the default mode ("not a candidate").

Two modes, selected with ``faithful``:

* ``faithful=True`` reproduces ``Multi_SLAM_Fusion.m``: a constant score vector normalises to
  NaN (MATLAB 0/0), NaN is skipped by max/min/top-k, unions keep duplicates.
* ``faithful=False`` (default) de-duplicates unions and maps a constant vector to all ones
  ("every entry is equally the best"), so no NaN appears.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, overload

import numpy as np

__all__ = [
    "DEFAULT_WEIGHTS",
    "Filled",
    "Spread",
    "combined_score",
    "default_weights",
    "flat_fusion",
    "mean_of",
    "minmax_normalise",
    "nan_argmax",
    "top_k",
    "union",
    "zscore",
]

#: Tier weights of the original scripts, tier 1 first (the paper's "1, 0.75, 0.5" from the
#: final tier backwards).
DEFAULT_WEIGHTS = (0.5, 0.75, 1.0)


def default_weights(n_tiers: int) -> tuple[float, ...]:
    """The original's weights aligned to the final tier: 1 tier -> (1,), 2 -> (0.75, 1), ..."""
    if n_tiers > len(DEFAULT_WEIGHTS):
        raise ValueError(f"{n_tiers} tiers need explicit weights (defaults cover 3)")
    return DEFAULT_WEIGHTS[len(DEFAULT_WEIGHTS) - n_tiers :]


@overload
def minmax_normalise(
    raw: Filled, higher_is_better: bool = False, *, faithful: bool = False
) -> Filled | np.ndarray: ...
@overload
def minmax_normalise(
    raw: np.ndarray, higher_is_better: bool = False, *, faithful: bool = False
) -> np.ndarray: ...
def minmax_normalise(
    raw: np.ndarray | Filled, higher_is_better: bool = False, *, faithful: bool = False
) -> np.ndarray | Filled:
    """Min-max normalise to best = 1, worst = 0 (NaN entries stay NaN and are ignored).

    Args:
        raw: (n,) raw scores (distances when ``higher_is_better`` is False).
        higher_is_better: direction of ``raw``.
        faithful: constant input gives NaN everywhere (MATLAB 0/0) instead of all ones.

    Returns:
        (n,) float64.
    """
    if isinstance(raw, Filled):
        return _minmax_filled(raw, higher_is_better, faithful=faithful)
    x = np.asarray(raw, dtype=np.float64)
    # fmin / fmax skip NaN without copying the non-NaN entries out (one pass each; a map of
    # a million references pays for every pass); NaN only when every entry is NaN.
    lo, hi = np.fmin.reduce(x, initial=np.nan), np.fmax.reduce(x, initial=np.nan)
    if np.isnan(lo):
        return np.full(x.shape, np.nan)
    if hi == lo:
        return np.full(x.shape, np.nan) if faithful else np.where(np.isnan(x), np.nan, 1.0)
    return (x - lo) / (hi - lo) if higher_is_better else (hi - x) / (hi - lo)


def _minmax_filled(raw: Filled, higher_is_better: bool, *, faithful: bool) -> Filled | np.ndarray:
    """:func:`minmax_normalise` of a :class:`Filled` vector from its entries and its fill:
    the same bounds and, at every reference, the same number (each is the same float64
    operation on the same value). A constant or empty vector: the whole array's result."""
    v = raw.values
    fill = np.float64(raw.fill) if raw.rest else np.float64(np.nan)
    lo, hi = np.fmin.reduce(v, initial=fill), np.fmax.reduce(v, initial=fill)
    if np.isnan(lo) or hi == lo:
        return minmax_normalise(np.asarray(raw), higher_is_better, faithful=faithful)
    if higher_is_better:
        values, filled = (v - lo) / (hi - lo), (np.float64(raw.fill) - lo) / (hi - lo)
    else:
        values, filled = (hi - v) / (hi - lo), (hi - np.float64(raw.fill)) / (hi - lo)
    return Filled(raw.n, raw.index, values, float(filled))


@overload
def mean_of(arrays: Sequence[Filled]) -> Filled: ...
@overload
def mean_of(arrays: Sequence[np.ndarray]) -> np.ndarray: ...
def mean_of(arrays: Sequence[np.ndarray] | Sequence[Filled]) -> np.ndarray | Filled:
    """``np.mean(arrays, axis=0)`` in float64 to the last bit (the sum in the given order,
    then divided by the count) without stacking them: over a whole map of a million
    references the stacked copy cost as much as the sum. At least one array.

    :class:`Filled` vectors only (an approximate tier 1's methods): a :class:`Filled` mean
    over the union of their entries, the same numbers as the whole arrays' mean."""
    if all(isinstance(x, Filled) for x in arrays):
        return _mean_filled(arrays)  # type: ignore[arg-type]  # (all Filled: checked)
    total = np.array(arrays[0], dtype=np.float64)
    for x in arrays[1:]:
        total += x
    total /= len(arrays)
    return total


def _mean_filled(vectors: Sequence[Filled]) -> Filled:
    first = vectors[0]
    if any(x.n != first.n for x in vectors):
        raise ValueError("vectors of different lengths")
    index = _union_index([x.index for x in vectors])
    total = first.at(index)
    fill = np.float64(first.fill)
    for x in vectors[1:]:
        total += x.at(index)
        fill += np.float64(x.fill)
    total /= len(vectors)
    fill /= len(vectors)
    return Filled(first.n, index, total, float(fill))


def _kth_largest_bound(s: np.ndarray, k: int, blocks: int = 1024) -> float:
    """A value <= the ``k``-th largest of ``s`` (no NaN, ``k < len(s)``) that few entries
    exceed: the ``k``-th largest of ``blocks`` block maxima (k distinct entries, so the top
    k are all at least as high), or the exact ``k``-th largest for short arrays, a large
    ``k``, or when ties at the bound would let through most of the array."""
    n = s.size
    if n >= 16 * blocks and 4 * k <= blocks:
        step = -(-n // blocks)
        maxima = np.maximum.reduceat(s, np.arange(0, n, step))
        bound = float(np.partition(maxima, maxima.size - k)[maxima.size - k])
        if np.count_nonzero(s >= bound) <= 64 * blocks:
            return bound
    return float(np.partition(s, n - k)[n - k])


def top_k(scores: np.ndarray | Filled, k: int) -> np.ndarray:
    """Indices of the ``k`` highest scores, descending; ties -> lower index; NaN skipped.

    This is the original's repeated max-then-blank selection. Fewer than ``k`` non-NaN
    entries give a shorter list.
    """
    if isinstance(scores, Filled) and k > 0:
        f = scores
        above = f.values > f.fill  # NaN: not above; nothing is above a NaN fill
        if f.rest and np.count_nonzero(above) >= k:
            # The k best are entries: every other reference holds the fill, below them.
            idx, v = f.index[above], f.values[above]
            return idx[np.lexsort((idx, -v))][:k].astype(np.int64)
    s = np.asarray(scores, dtype=np.float64)
    if k <= 0 or s.size == 0:
        return np.zeros(0, dtype=np.int64)
    if k < s.size and not np.isnan(s).any():
        # No NaN (a whole-database tier): every entry of the top k is >= the k-th largest of
        # any k distinct entries, e.g. of block maxima (one pass); order what passes.
        kth = _kth_largest_bound(s, k)
        keep = np.flatnonzero(s >= kth)
        return keep[np.lexsort((keep, -s[keep]))][:k].astype(np.int64)
    valid = np.flatnonzero(~np.isnan(s))
    if valid.size == 0:
        return np.zeros(0, dtype=np.int64)
    v = s[valid]
    if k < valid.size:
        # Partial selection, then an exact stable ordering of the survivors.
        kth = np.partition(-v, k - 1)[k - 1]
        keep = np.flatnonzero(-v <= kth)
        order = keep[np.lexsort((valid[keep], -v[keep]))][:k]
    else:
        order = np.lexsort((valid, -v))
    return valid[order].astype(np.int64)


def union(lists: Sequence[np.ndarray], *, faithful: bool = False) -> np.ndarray:
    """Combine per-method candidate lists of a tier.

    Faithful: plain concatenation, duplicates kept (length = sum of lengths). Default: the
    same order with later repeats removed.
    """
    cat = (
        np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])
        if lists
        else np.zeros(0, np.int64)
    )
    if faithful:
        return cat
    _, first = np.unique(cat, return_index=True)
    return cat[np.sort(first)]


def zscore(x: np.ndarray) -> np.ndarray:
    """MATLAB ``zscore``: sample std (n - 1); constant or single entry -> zeros; NaN -> all NaN."""
    v = np.asarray(x, dtype=np.float64)
    if v.size == 0:
        return v.copy()
    if np.isnan(v).any():
        return np.full(v.shape, np.nan)
    if v.size == 1:
        return np.zeros_like(v)
    sd = v.std(ddof=1)
    if sd == 0:
        return np.zeros_like(v)
    return (v - v.mean()) / sd


def nan_argmax(x: np.ndarray) -> int:
    """MATLAB ``max`` index: first maximum, NaN skipped; all NaN -> 0."""
    v = np.asarray(x, dtype=np.float64)
    if v.size == 0 or np.isnan(v).all():
        return 0
    return int(np.nanargmax(v))


def combined_score(
    tier_values: Sequence[np.ndarray], weights: Sequence[float], *, faithful: bool = False
) -> np.ndarray:
    """Cross-tier Combined score over the final candidates (spec §5.3).

    Args:
        tier_values: per tier, the (F,) tier score gathered at the final candidates: the
            element-wise max over a non-final tier's methods, the mean for the final tier.
        weights: per tier, tier 1 first.
        faithful: NaN semantics of the original (constant vector -> NaN).

    Returns:
        (F,) ``Dsuper = sum_t w_t * minmax(x_t)``; z-score it with :func:`zscore`.
    """
    if len(tier_values) != len(weights):
        raise ValueError("one weight per tier is required")
    total: np.ndarray | None = None
    for x, w in zip(tier_values, weights, strict=True):
        part = minmax_normalise(x, higher_is_better=True, faithful=faithful) * float(w)
        total = part if total is None else total + part
    assert total is not None
    return total


def flat_fusion(
    raw_by_method: Sequence[np.ndarray], higher_is_better: Sequence[bool], *, faithful: bool = False
) -> np.ndarray:
    """Parallel (flat) fusion baseline: mean of each method's whole-database normalised score.

    Args:
        raw_by_method: per method, (N,) raw scores of one query against the whole database.
        higher_is_better: per method, the direction of its raw score.

    Returns:
        (N,) fused score, higher is better.
    """
    norm = [
        minmax_normalise(r, h, faithful=faithful)
        for r, h in zip(raw_by_method, higher_is_better, strict=True)
    ]
    return np.mean(norm, axis=0)


class Filled:
    """An ``(n,)`` float64 score vector that holds one value, ``fill``, everywhere except at
    ``index`` (ascending, unique), where it holds ``values``: an approximate tier 1's scores
    over a map of a million references (the sample and FAISS's candidates scored exactly,
    every other reference their worst). :func:`minmax_normalise`, :func:`top_k` and
    :func:`mean_of` work on the entries and the fill, with the whole array's results;
    ``np.asarray(filled)`` makes the whole array (a new one each time)."""

    __slots__ = ("fill", "index", "n", "values")

    def __init__(self, n: int, index: np.ndarray, values: np.ndarray, fill: float) -> None:
        self.n = int(n)
        self.index = np.asarray(index, dtype=np.int64)
        self.values = np.asarray(values, dtype=np.float64)
        self.fill = float(fill)
        if self.index.shape != self.values.shape or self.index.ndim != 1:
            raise ValueError("index and values must be (m,) arrays of one length")

    @property
    def rest(self) -> int:
        """How many references hold the fill."""
        return self.n - len(self.index)

    @property
    def shape(self) -> tuple[int]:
        return (self.n,)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.float64)

    def __len__(self) -> int:
        return self.n

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = np.full(self.n, self.fill)
        whole[self.index] = self.values
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def __getitem__(self, key: Any) -> np.ndarray:
        return np.asarray(self)[key]

    def at(self, idx: np.ndarray) -> np.ndarray:
        """``np.asarray(self)[idx]`` for an array of indices, read from the entries."""
        return _entries_at(self.index, self.values, np.asarray(idx, dtype=np.int64), self.fill)


def _union_index(indices: Sequence[np.ndarray]) -> np.ndarray:
    """The ascending union of :class:`Filled` vectors' indices (the first one itself when
    they are all equal, as an approximate tier 1's methods often are: no copy)."""
    if not indices:
        return np.zeros(0, np.int64)
    first = indices[0]
    if all(x is first or np.array_equal(x, first) for x in indices[1:]):
        return first
    return np.unique(np.concatenate(indices))


def _entries_at(index: np.ndarray, values: np.ndarray, idx: np.ndarray, fill: float) -> np.ndarray:
    """``values`` at ``idx`` where ``index`` (ascending) holds it, ``fill`` elsewhere."""
    out = np.full(len(idx), fill)
    if len(index):
        pos = np.minimum(np.searchsorted(index, idx), len(index) - 1)
        hit = index[pos] == idx
        out[hit] = values[pos[hit]]
    return out


class Spread(Mapping[str, np.ndarray]):
    """Per method, an ``(n,)`` array that is NaN (or the method's ``fill``) except at
    ``index`` (ascending, unique), where it holds ``entries[method]``: a later tier's
    scores, which cover a few candidates of a database that may hold a million references,
    or an approximate tier 1's (:class:`Filled`, :meth:`of_filled`). Reading a method
    (``spread[m]``) makes its whole array once (the same values the tier always reported);
    :meth:`at`, :meth:`best` and :meth:`filled` read the entries without making it.
    """

    def __init__(
        self,
        n: int,
        index: np.ndarray,
        entries: Mapping[str, np.ndarray],
        fill: Mapping[str, float] | None = None,
    ) -> None:
        self.n = int(n)
        self.index = np.asarray(index, dtype=np.int64)
        self.entries = {m: np.asarray(v, dtype=np.float64) for m, v in entries.items()}
        #: per method, what it holds outside ``index`` (NaN where not given)
        self.fill = {m: float((fill or {}).get(m, np.nan)) for m in self.entries}
        self._whole: dict[str, np.ndarray] = {}

    @classmethod
    def of_filled(cls, n: int, vectors: Mapping[str, Filled]) -> Spread:
        """The :class:`Filled` vectors of one tier's methods on the union of their entries."""
        mids = list(vectors)
        index = _union_index([vectors[m].index for m in mids])
        return cls(
            n,
            index,
            {m: vectors[m].at(index) for m in mids},
            {m: vectors[m].fill for m in mids},
        )

    def filled(self, mid: str) -> Filled:
        """Method ``mid`` as a :class:`Filled` vector (its fill outside the entries)."""
        return Filled(self.n, self.index, self.entries[mid], self.fill[mid])

    def __getitem__(self, mid: str) -> np.ndarray:
        if mid not in self._whole:
            whole = np.full(self.n, self.fill[mid])
            whole[self.index] = self.entries[mid]
            self._whole[mid] = whole
        return self._whole[mid]

    def __iter__(self) -> Iterator[str]:
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def at(self, mid: str, idx: np.ndarray) -> np.ndarray:
        """``self[mid][idx]``, read from the entries."""
        idx = np.asarray(idx, dtype=np.int64)
        return _entries_at(self.index, self.entries[mid], idx, self.fill[mid])

    def best(self, mid: str) -> int:
        """``nanargmax(self[mid])`` (the lowest index among equal bests), -1 without a
        finite entry."""
        v = self.entries[mid]
        fill = self.fill[mid]
        if not np.isnan(fill) and len(self.index) < self.n and not (v > fill).any():
            whole = self[mid]  # the fill is the best, or ties with it: the whole array
            fin = np.isfinite(whole)
            return int(np.nanargmax(np.where(fin, whole, np.nan))) if fin.any() else -1
        finite = np.isfinite(v)
        if not finite.any():
            return -1
        return int(self.index[np.nanargmax(np.where(finite, v, np.nan))])
