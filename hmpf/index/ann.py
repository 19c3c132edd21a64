"""FAISS indexes for tier-1 global methods: metric detection, build, search.

A method does not declare its distance, so it is *detected* from the method itself: its
``pairwise`` scores on a sample of reference vectors are compared with FAISS's metrics,

* ``l2``: Euclidean (FAISS returns squared distances; the square root is taken),
* ``l1``: sum of absolute differences (SAD's mean absolute difference is ``l1 / D``),
* ``ip``: inner product (cosine similarity on normalised CNN descriptors),

each up to a constant factor (``raw = scale * metric``). A method whose scores match none gets
no FAISS index (tier 1 then scans the stored matrix; approximate types are refused). Types
that cannot search with L1 (PQ) fall back to L2 as a *proxy* to generate candidates; the
candidates are always re-scored exactly by the method (see :mod:`hmpf.index.reader`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hmpf.errors import MissingDependencyError
from hmpf.index.layout import IndexBuildError, IndexCorruptError
from hmpf.methods import Method

__all__ = [
    "MetricSpec",
    "build_faiss",
    "detect_metric",
    "faiss_module",
    "is_exact_factory",
    "read_faiss",
    "to_raw",
]

MetricKind = Literal["l2", "l1", "ip"]
_PROBE_ROWS = 32


def faiss_module() -> Any:
    """Import faiss, or tell the user which extra to install."""
    try:
        import faiss
    except ImportError:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(
            "the index needs FAISS and h5py: pip install 'hmpf[index]'"
        ) from None
    return faiss


@dataclass(frozen=True)
class MetricSpec:
    """How FAISS values map to the method's raw score: ``raw = scale * value``.

    Attributes:
        kind: FAISS metric used for search.
        scale: factor from the FAISS value (after ``sqrt`` for l2) to the raw score.
        proxy: True when ``kind`` only approximates the method's distance (candidates are
            re-scored exactly).
    """

    kind: MetricKind
    scale: float
    proxy: bool = False

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _candidates(a: np.ndarray, b: np.ndarray) -> dict[str, np.ndarray]:
    d = a[:, None, :] - b[None, :, :]
    return {
        "l2": np.sqrt((d * d).sum(-1)),
        "l1": np.abs(d).sum(-1),
        "ip": a @ b.T,
    }


def detect_metric(method: Method, matrix: np.ndarray) -> MetricSpec | None:
    """The FAISS metric reproducing ``method.pairwise`` on ``matrix``'s rows, or None.

    Args:
        method: a global method.
        matrix: (N, D) stored reference vectors (any dtype).
    """
    if method.kind != "global" or matrix.shape[0] < 2:
        return None
    step = max(1, matrix.shape[0] // _PROBE_ROWS)
    sample = np.asarray(matrix[::step][:_PROBE_ROWS])
    scores = np.asarray(method.pairwise(sample, sample), dtype=np.float64)  # type: ignore[attr-defined]
    x = sample.astype(np.float64)
    for kind, cand in _candidates(x, x).items():
        denom = float((cand * cand).sum())
        if denom == 0.0:
            continue
        scale = float((scores * cand).sum() / denom)
        tol = 1e-4 * max(1e-12, float(np.abs(scores).max()))
        if scale == 0.0 or not np.allclose(scores, scale * cand, rtol=1e-4, atol=tol):
            continue
        # FAISS ranks l2 / l1 ascending and ip descending: the method must agree.
        ascending = (kind != "ip") == (scale > 0)
        if ascending == method.higher_is_better:
            continue
        return MetricSpec(kind, scale)  # type: ignore[arg-type]
    return None


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
