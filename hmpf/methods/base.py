"""Method interface: the base class checks input, subclasses compute.

A method turns an RGB image into a *feature* and compares a query's feature with reference
features, giving one raw score per reference. Two kinds exist (ARCHITECTURE.md):

* ``global``: one fixed-length vector per image; compared by a distance over stacked matrices,
  so it can rank the whole database (tier 1, later through FAISS).
* ``local``: a variable-size set per image (keypoints, regions); compared pairwise, so it is
  used on candidate lists.

``higher_is_better`` says which direction of the raw score is better; fusion normalises every
score to ``best = 1`` (METHODS.md §5.1).
"""

from __future__ import annotations

import hashlib
import json
import weakref
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from hmpf.imageio import to_rgb

__all__ = ["GlobalMethod", "LocalMethod", "Method", "MethodConfig"]


class MethodConfig(BaseModel):
    """Base of every method's typed configuration: frozen, unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Method(ABC):
    """One image-matching technique.

    Subclasses set the class attributes and implement :meth:`_extract` plus the comparison of
    their kind. ``version`` is part of the cache key: bump it whenever the feature a method
    produces changes, so that stale cached descriptors are never reused.
    """

    name: ClassVar[str]
    kind: ClassVar[Literal["global", "local"]]
    higher_is_better: ClassVar[bool] = False
    version: ClassVar[str] = "2"
    Config: ClassVar[type[MethodConfig]] = MethodConfig

    def __init__(self, config: MethodConfig | None = None) -> None:
        self.config = config if config is not None else self.Config()

    # -- extraction -------------------------------------------------------------------------
    def extract(self, image: np.ndarray) -> Any:
        """Compute this method's feature for one H x W x 3 RGB ``uint8`` image."""
        return self._extract(to_rgb(image))

    @abstractmethod
    def _extract(self, image: np.ndarray) -> Any: ...

    # -- comparison -------------------------------------------------------------------------
    @abstractmethod
    def scores(self, query: Any, references: Any, subset: np.ndarray | None = None) -> np.ndarray:
        """Raw scores of one query feature against ``references`` (a stored feature set).

        Args:
            query: the query's feature as returned by :meth:`extract`.
            references: the stored set as returned by :meth:`stack`.
            subset: optional reference indices (candidates); ``None`` means all.

        Returns:
            float64 array, one raw score per reference (or per entry of ``subset``, in order).
        """

    @abstractmethod
    def stack(self, features: Sequence[Any]) -> Any:
        """Combine per-image features into the stored set used by :meth:`scores`."""

    # -- persistence ------------------------------------------------------------------------
    def to_arrays(self, feature: Any) -> dict[str, np.ndarray]:
        """Feature -> named numpy arrays (for the descriptor cache and the index)."""
        return {"x": np.asarray(feature)}

    def from_arrays(self, arrays: dict[str, np.ndarray]) -> Any:
        """Inverse of :meth:`to_arrays`."""
        return arrays["x"]

    # -- parameters fitted on the reference set --------------------------------------------
    def requires_fit(self) -> bool:
        """True when :meth:`fit_state` must be set (from the references) before extraction.

        Fitted parameters (VLAD centroids, PCA, a visual vocabulary) belong to the reference
        set: they are fitted once on it, stored with it (the index), and never refitted for a
        query.
        """
        return False

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The fitted parameters as named arrays (empty for methods without any)."""
        return {}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Set the fitted parameters from :meth:`state_arrays` output."""
        if arrays:
            raise ValueError(f"method {self.name!r} has no fitted parameters")

    def state_digest(self) -> str:
        """sha256 of the fitted parameters ('' when there are none)."""
        arrays = self.state_arrays()
        if not arrays:
            return ""
        h = hashlib.sha256()
        for k in sorted(arrays):
            a = np.ascontiguousarray(arrays[k])
            h.update(f"{k}:{a.dtype.str}:{a.shape}".encode())
            h.update(a.tobytes())
        return h.hexdigest()

    def cache_key(self) -> str:
        """Stable id of this method's exact output: name, code version, config, fitted state."""
        payload = json.dumps(
            {
                "name": self.name,
                "version": self.version,
                "config": self.config.model_dump(),
                "state": self.state_digest(),
            },
            sort_keys=True,
        )
        return f"{self.name}-{hashlib.sha256(payload.encode()).hexdigest()[:16]}"

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config!r})"

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuilt from the config (and fitted state) in worker processes: OpenCV objects and
        # torch modules do not pickle.
        return (_rebuild, (type(self), self.config, self.state_arrays()))


def _rebuild(cls: type[Method], config: MethodConfig, state: dict[str, np.ndarray]) -> Method:
    method = cls(config)
    if state:
        method.load_state(state)
    return method


class GlobalMethod(Method):
    """A method with one vector per image; the stored set is an N x D matrix."""

    kind: ClassVar[Literal["global", "local"]] = "global"
    # Descriptor length: a class default, set per instance where the config decides it.
    dim: int

    def stack(self, features: Sequence[np.ndarray]) -> np.ndarray:
        if len(features) == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([np.asarray(f) for f in features])

    def scores(
        self, query: np.ndarray, references: np.ndarray, subset: np.ndarray | None = None
    ) -> np.ndarray:
        refs = references if subset is None else references[np.asarray(subset, dtype=np.int64)]
        return self.pairwise(np.asarray(query)[None, :], refs)[0]

    @abstractmethod
    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        """(nq, D) x (n, D) -> (nq, n) float64 raw scores."""


class LocalMethod(Method):
    """A method with a variable-size feature set per image; the stored set is a list."""

    kind: ClassVar[Literal["global", "local"]] = "local"

    def stack(self, features: Sequence[Any]) -> Any:
        """A list by default; subclasses may return their own indexed set type."""
        return list(features)


_REF_CACHE: dict[int, tuple[Any, np.ndarray, np.ndarray]] = {}
_REF_CACHE_SIZE = 8


def _as_f64_with_norms(references: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``references`` in float64 and their squared row norms, remembered per array.

    A hierarchy scores one query at a time against the same reference matrix; converting
    it to float64 and summing its squares again for every query dominated the per-query
    cost on large maps. The entry lives as long as the array does (weak reference).
    """
    key = id(references)
    hit = _REF_CACHE.get(key)
    if hit is not None and hit[0]() is references:
        return hit[1], hit[2]
    r = np.asarray(references, dtype=np.float64)
    norms = (r * r).sum(1)
    try:
        ref = weakref.ref(references)
    except TypeError:  # not weak-referenceable (e.g. a list): do not remember it
        return r, norms
    if len(_REF_CACHE) >= _REF_CACHE_SIZE:
        _REF_CACHE.pop(next(iter(_REF_CACHE)))
    _REF_CACHE[key] = (ref, r, norms)
    return r, norms


def euclidean(queries: np.ndarray, references: np.ndarray) -> np.ndarray:
    """Euclidean distances (nq, D) x (n, D) -> (nq, n) float64, exact to rounding.

    Uses the ``|q|^2 + |r|^2 - 2 q.r`` expansion in float64 (clipped at 0): fast for the
    full-database matrices and accurate enough for descriptors of moderate norm. The
    float64 copy of a large reference matrix and its norms are computed once per matrix.
    """
    q = np.asarray(queries, dtype=np.float64)
    if isinstance(references, np.ndarray) and references.size >= 1 << 16:
        r, rn = _as_f64_with_norms(references)
    else:
        r = np.asarray(references, dtype=np.float64)
        rn = (r * r).sum(1)
    d2 = (q * q).sum(1)[:, None] + rn[None, :] - 2.0 * (q @ r.T)
    return np.sqrt(np.maximum(d2, 0.0))
