"""FAISS indexes for tier-1 global methods: declared metric, build, search.

Every global method declares the FAISS metric reproducing its scores
(:meth:`~hmpf.methods.base.GlobalMethod.faiss_metric`), up to a constant factor
(``raw = scale * metric``):

* ``l2``: Euclidean (FAISS returns squared distances; the square root is taken),
* ``l1``: sum of absolute differences (SAD's mean absolute difference is ``l1 / D``),
* ``ip``: inner product (cosine similarity on normalised CNN descriptors).

A method that declares None gets no FAISS index (tier 1 then scans the stored matrix;
approximate types are refused); one that declares nothing is an error. Types that cannot
search with L1 (PQ) fall back to L2 as a *proxy* to generate candidates; the candidates are
always re-scored exactly by the method (see :mod:`hmpf.index.reader`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hmpf.errors import MissingDependencyError
from hmpf.index.layout import IndexBuildError, IndexCorruptError
from hmpf.methods import GlobalMethod, Method
from hmpf.methods.base import MetricKind, MetricSpec

__all__ = [
    "MetricSpec",
    "build_faiss",
    "declared_metric",
    "faiss_module",
    "is_exact_factory",
    "read_faiss",
    "to_raw",
]


def faiss_module() -> Any:
    """Import faiss, or tell the user which extra to install."""
    try:
        import faiss  # the index extra
    except ImportError:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(
            "the index needs FAISS and h5py: pip install 'hmpf[index]'"
        ) from None
    return faiss


def declared_metric(mid: str, method: Method) -> MetricSpec | None:
    """The FAISS metric tier-1 method ``mid`` declares (None: it has none).

    Raises:
        IndexBuildError: ``method`` is not global, or declares no metric at all.
    """
    if not isinstance(method, GlobalMethod):
        raise IndexBuildError(f"method {mid!r} ({method.name}) is not global: no FAISS index")
    try:
        return method.faiss_metric()
    except NotImplementedError:
        raise IndexBuildError(
            f"method {mid!r}: {type(method).__name__} declares no FAISS metric, so it cannot "
            "serve tier 1; give it a faiss_metric() (None when no FAISS metric reproduces "
            "its scores)"
        ) from None


def is_exact_factory(factory: str) -> bool:
    """True for FAISS factory strings that search exhaustively and exactly."""
    return factory.replace(" ", "") in ("Flat", "IDMap,Flat")


def _faiss_metric(kind: MetricKind) -> int:
    faiss = faiss_module()
    return {
        "l2": faiss.METRIC_L2,
        "l1": faiss.METRIC_L1,
        "ip": faiss.METRIC_INNER_PRODUCT,
    }[kind]


def _make(factory: str, x: np.ndarray, kind: MetricKind) -> Any:
    faiss = faiss_module()
    try:
        index = faiss.index_factory(x.shape[1], factory, _faiss_metric(kind))
    except RuntimeError as exc:
        raise IndexBuildError(f"FAISS factory string {factory!r}: {_first_line(exc)}") from None
    if not index.is_trained:
        try:
            index.train(x)
        except RuntimeError as exc:
            raise IndexBuildError(
                f"FAISS {factory!r} cannot be trained on {len(x)} references "
                f"({_first_line(exc)}); use 'Flat' for small maps"
            ) from None
    index.add(x)
    index.search(x[:1], 1)  # some types cannot search some metrics (PQ with L1)
    return index


def _first_line(exc: BaseException) -> str:
    lines = [s for s in str(exc).splitlines() if s.strip()]
    return lines[-1][:200] if lines else type(exc).__name__


def build_faiss(
    matrix: np.ndarray, metric: MetricSpec, factory: str, params: str = ""
) -> tuple[Any, MetricSpec]:
    """Build and fill a FAISS index on the (N, D) references.

    Returns:
        The index and the metric actually used (an L2 proxy when ``factory`` cannot search
        the method's L1 distance).
    """
    x = np.ascontiguousarray(matrix, dtype=np.float32)
    try:
        index = _make(factory, x, metric.kind)
    except RuntimeError:
        if metric.kind != "l1":
            raise
        metric = MetricSpec("l2", 1.0, proxy=True)
        index = _make(factory, x, "l2")
    if params:
        set_search_params(index, params)
    return index, metric


def set_search_params(index: Any, params: str) -> None:
    """Apply a FAISS ParameterSpace string (e.g. ``"nprobe=16"``, ``"efSearch=64"``)."""
    faiss = faiss_module()
    try:
        faiss.ParameterSpace().set_index_parameters(index, params)
    except RuntimeError as exc:
        raise IndexBuildError(f"FAISS search parameters {params!r}: {_first_line(exc)}") from None


def read_faiss(path: Path, params: str = "") -> Any:
    """Load a FAISS index file (corruption -> :class:`IndexCorruptError` naming the file)."""
    faiss = faiss_module()
    try:
        index = faiss.read_index(str(path))
    except RuntimeError as exc:
        raise IndexCorruptError(
            f"{path}: unreadable FAISS index ({_first_line(exc)}); run `hmpf-index verify`"
        ) from None
    if params:
        set_search_params(index, params)
    return index


def to_raw(values: np.ndarray, metric: MetricSpec) -> np.ndarray:
    """FAISS distances / similarities -> the method's raw scores (float64)."""
    v = np.asarray(values, dtype=np.float64)
    if metric.kind == "l2":
        v = np.sqrt(np.maximum(v, 0.0))
    return v * metric.scale
