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

import math
import re
from pathlib import Path
from typing import Any, NamedTuple

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
    "search_faiss",
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


#: ``PCA<D>:<d>,<codes>[,B<b>[x<G>] | ,S<e>[x<G>] | ,FS<M>[x<G>] | ,PQ<M>x4fs | ,HNSW<M>][,k<F>]``:
#: hmpf's own tier-1 type (see :func:`projected_scan`)
_PROJECTED = re.compile(
    r"^PCA(\d+):(\d+),(SQfp16|SQ8)"
    r"(?:,B([1-9]\d*)(?:x(\d+))?|,PQ([1-9]\d*)x4fs|,HNSW([1-9]\d*)|,S([1-9]\d*)(?:x(\d+))?"
    r"|,FS([1-9]\d*)(?:x(\d+))?)?"
    r"(?:,k(\d+))?$"
)


class ProjectedSpec(NamedTuple):
    """A projected-scan factory string's parts (see :func:`projected_scan`)."""

    big: int  #: D, the dimensions kept and re-ranked on
    small: int  #: d, the dimensions of the short scan
    codes: str  #: ``SQfp16`` or ``SQ8``
    k_factor: int  #: F: the short scan keeps F x k rows for the re-ranking on D
    bits: int = 0  #: b: 0, or the sign bits of a binary scan in front of the short scan
    bit_factor: int = 0  #: G: the binary scan keeps G x F x k rows for the short scan
    pq: int = 0  #: M: 0, or the short scan reads 4-bit fast-scan PQ codes of M sub-quantizers
    hnsw: int = 0  #: M: 0, or the short list comes from an HNSW graph of M links per row
    pre: int = 0  #: e: 0, or the 8-bit codes of the first e dimensions scanned in front
    pre_factor: int = 0  #: G: the scan in front keeps G x F x k rows for the short scan
    fast: int = 0  #: M: 0, or 4-bit fast-scan PQ codes (M sub-quantizers) of the first d in front
    fast_factor: int = 0  #: G: the fast scan in front keeps G x F x k rows for the short scan


def projected_spec(factory: str) -> ProjectedSpec | None:
    """The parts of a projected-scan factory string, else None."""
    m = _PROJECTED.match(factory.replace(" ", ""))
    if m is None:
        return None
    bits = int(m[4] or 0)
    pre = int(m[8] or 0)
    fast = int(m[10] or 0)
    return ProjectedSpec(
        int(m[1]),
        int(m[2]),
        m[3],
        int(m[12] or PROJECTED_K_FACTOR),
        bits,
        int(m[5] or PROJECTED_BIT_FACTOR) if bits else 0,
        int(m[6] or 0),
        int(m[7] or 0),
        pre,
        int(m[9] or PROJECTED_PRE_FACTOR) if pre else 0,
        fast,
        int(m[11] or PROJECTED_FAST_FACTOR) if fast else 0,
    )


#: candidates of the short scan per row a projected-scan index returns (its default)
PROJECTED_K_FACTOR = 8
#: candidates of the binary scan per candidate of the short scan (its default)
PROJECTED_BIT_FACTOR = 8
#: candidates of the 8-bit scan in front per candidate of the short scan (its default)
PROJECTED_PRE_FACTOR = 4
#: candidates of the fast scan in front per candidate of the short scan (its default)
PROJECTED_FAST_FACTOR = 8
#: the candidate list an HNSW short list is built with (FAISS's default)
HNSW_EF_CONSTRUCTION = 40


def pca_rows(x: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean of the (N, D) rows ``x`` and their top ``dim`` principal directions
    ((dim, D), orthonormal rows, largest variance first)."""
    from scipy.linalg import eigh  # a build-time need only: readers never fit a PCA

    x = np.asarray(x, dtype=np.float32)
    n, d = x.shape
    if not 0 < dim < d:
        raise IndexBuildError(f"PCA to {dim} dimensions of {d}-dimensional rows")
    if n < 2:
        raise IndexBuildError(f"a PCA needs 2 references or more, got {n}")
    mean = x.mean(axis=0, dtype=np.float64)
    xc = (x - mean.astype(np.float32)).astype(np.float32)
    cov = (xc.T @ xc).astype(np.float64)
    _, vec = eigh(cov, subset_by_index=[d - dim, d - 1])
    return mean, np.ascontiguousarray(vec[:, ::-1].T)


def projected_scan(x: np.ndarray, factory: str) -> Any:
    """A trained, empty projected-scan FAISS index for the (N, D) rows ``x`` (L2).

    ``PCA<D>:<d>,<codes>[,B<b>[x<G>] | ,S<e>[x<G>] | ,FS<M>[x<G>] | ,PQ<M>x4fs | ,HNSW<M>]
    [,k<F>]``: rows
    projected on their top ``D`` principal directions (centred on their mean) and stored as
    ``codes`` (``SQfp16``: 2 bytes a dimension; ``SQ8``: 1); a search scans every row on the
    first ``d`` of those dimensions, keeps the ``F`` x ``k`` nearest and re-ranks them on all
    ``D`` (FAISS: a PCA ``LinearTransform`` in front of an ``IndexRefine`` whose base sees
    the first ``d`` dimensions). No partition: every row is looked at, which keeps the
    neighbours that IVF's lists lose where distances are concentrated (NetVLAD), at
    ``(D + d) x codes`` bytes per row. ``F`` is also the search parameter ``k_factor_rf``.

    With ``B<b>``, the scan of every row reads ``b`` bits instead: the signs of the first
    ``b`` centred dimensions (``b <= D``) after an ITQ rotation (:func:`_sign_codes`),
    compared by Hamming distance; the ``G`` x ``F`` x ``k`` nearest by it (``G`` 8 by
    default, set at build; the search parameter ``k_factor_front``) go on to the short scan
    on ``d`` dimensions, which then compares only those. ``b / 8`` bytes more per row; the
    scan reads ``b / 8`` bytes of each row instead of ``d x codes``.

    With ``S<e>``, the scan of every row reads the first ``e`` dimensions (``e < d``) as
    8-bit scalar codes (FAISS's ``SQ8``: 256 even steps between each dimension's least and
    greatest value in the training rows); the ``G`` x ``F`` x ``k`` nearest by them (``G``
    4 by default, set at build; the search parameter ``k_factor_front``) go on to the short
    scan on ``d`` dimensions, which then compares only those. ``e`` bytes more per row; the
    scan reads ``e`` bytes of each row instead of ``d x codes``. The leading principal
    directions hold most of a descriptor's variance: on the scale bench's million
    references (``S32x4`` for GeM, ``S64x4`` for NetVLAD) it keeps the plain scan's recall
    against exact search (docs/scale.md).

    With ``FS<M>``, the scan of every row in front reads FAISS's 4-bit fast-scan product
    codes of the first ``d`` dimensions (``M`` sub-quantizers of ``d / M`` dimensions, 16
    centroids each: ``M / 2`` bytes per row, compared by SIMD table look-ups); the ``G`` x
    ``F`` x ``k`` nearest by them (``G`` 8 by default, set at build; the search parameter
    ``k_factor_front``) go on to the short scan on ``d`` dimensions of the scalar codes,
    which then compares only those. ``M / 2`` bytes more per row, read into the process (a
    fast-scan table is not memory-mapped). Where the short scan's ``F`` x ``k`` from these
    codes alone lost neighbours (``PQ<M>x4fs`` below), a list ``G`` times as long keeps them
    for the scalar codes to sort out. On the scale bench's million references ``FS32x4``
    (GeM, two dimensions a sub-quantizer) and ``FS128x8`` (NetVLAD, one) keep the exact top
    100; NetVLAD with two dimensions a sub-quantizer (``FS64``) did not (docs/scale.md).

    With ``PQ<M>x4fs``, the short scan reads FAISS's 4-bit fast-scan product codes of the
    first ``d`` dimensions instead (``M`` sub-quantizers of ``d / M`` dimensions, 16
    centroids each: ``M / 2`` bytes per row, compared by SIMD table look-ups, an order of
    magnitude faster than scanning scalar codes); its ``F`` x ``k`` nearest are re-ranked on
    all ``D`` as before. The scalar codes of the first ``d`` dimensions are then not stored.

    With ``HNSW<M>``, no row is scanned: the short list is the ``F`` x ``k`` rows an HNSW
    graph (Malkov & Yashunin, TPAMI 2020; FAISS's ``IndexHNSWSQ``, ``M`` links per row,
    ``efConstruction`` 40) finds on the first ``d`` dimensions' ``codes``, searched with a
    candidate list of ``max(efSearch, F x k)`` rows (``efSearch``: a search parameter, 16
    by default, so the list is the short list's size unless set higher). A search then costs
    about the logarithm of the map's size instead of its size; what the graph misses never
    reaches the re-ranking, so its recall is measured on real descriptors like every other
    type's. Search it through :func:`search_faiss`, which sets the candidate list for each
    search (FAISS itself would search with ``efSearch`` only). The graph (about ``2 M`` x 4
    bytes a row) is read into the process, not memory-mapped. On the scale bench's million
    references it keeps GeM's exact neighbours but loses NetVLAD's (docs/scale.md).
    """
    faiss = faiss_module()
    spec = projected_spec(factory)
    assert spec is not None
    big, small, codes, k_factor, bits, bit_factor, pq, hnsw, pre, pre_factor, fast, fast_factor = (
        spec
    )
    d = x.shape[1]
    if not small < big < d:
        raise IndexBuildError(
            f"FAISS factory string {factory!r}: needs {small} < {big} < {d} (the rows' size)"
        )
    if bits and not (0 < bits <= big and bit_factor > 0):
        raise IndexBuildError(
            f"FAISS factory string {factory!r}: needs 0 < {bits} <= {big} sign bits and "
            "a factor above 0"
        )
    if pre and not (pre < small and pre_factor > 0):
        raise IndexBuildError(
            f"FAISS factory string {factory!r}: needs {pre} < {small} dimensions in front and "
            "a factor above 0"
        )
    for m in (pq, fast):
        if m and small % m:
            raise IndexBuildError(
                f"FAISS factory string {factory!r}: {m} sub-quantizers do not divide {small} "
                "dimensions"
            )
    if fast and fast_factor < 1:
        raise IndexBuildError(
            f"FAISS factory string {factory!r}: needs a factor above 0 for the fast scan"
        )
    mean, comps = pca_rows(x, big)
    pca = faiss.LinearTransform(d, big, True)
    faiss.copy_array_to_vector(comps.astype(np.float32).ravel(), pca.A)
    faiss.copy_array_to_vector((-(comps @ mean)).astype(np.float32), pca.b)
    pca.is_trained = True
    qtype = getattr(faiss.ScalarQuantizer, "QT_fp16" if codes == "SQfp16" else "QT_8bit")
    if pq:
        codes_of_short = faiss.IndexPQFastScan(small, pq, 4)
    elif hnsw:
        codes_of_short = faiss.IndexHNSWSQ(small, qtype, hnsw)
        codes_of_short.hnsw.efConstruction = HNSW_EF_CONSTRUCTION
    else:
        codes_of_short = faiss.IndexScalarQuantizer(small, qtype)
    short = faiss.IndexPreTransform(_leading(big, small), codes_of_short)
    full = faiss.IndexScalarQuantizer(big, qtype)
    y = pca.apply(np.ascontiguousarray(x, dtype=np.float32))
    full.train(y)
    short.train(y)
    scan = short
    front = None  # a scan of every row in front of the short scan, and its factor
    if bits:
        front, factor = _sign_codes(y, bits), bit_factor
    elif pre:
        front = faiss.IndexPreTransform(
            _leading(big, pre), faiss.IndexScalarQuantizer(pre, faiss.ScalarQuantizer.QT_8bit)
        )
        front.train(y)
        factor = pre_factor
    elif fast:
        front = faiss.IndexPreTransform(_leading(big, small), faiss.IndexPQFastScan(small, fast, 4))
        front.train(y)
        factor = fast_factor
    if front is not None:
        scan = faiss.IndexRefine(front, short)
        scan.k_factor = float(factor)
        scan.is_trained = True
    refine = faiss.IndexRefine(scan, full)
    refine.k_factor = float(k_factor)
    index = faiss.IndexPreTransform(pca, refine)
    refine.is_trained = True
    index.is_trained = True
    return index


def _leading(big: int, dims: int) -> Any:
    """A FAISS transform keeping the first ``dims`` of ``big`` coordinates."""
    faiss = faiss_module()
    keep = faiss.LinearTransform(big, dims, False)
    faiss.copy_array_to_vector(np.eye(dims, big, dtype=np.float32).ravel(), keep.A)
    keep.is_trained = True
    return keep


def _sign_codes(y: np.ndarray, bits: int) -> Any:
    """An empty index of ``bits`` sign bits for rows ``y`` (centred principal coordinates,
    largest variance first), compared by Hamming distance: the first ``bits`` coordinates
    turned by an ITQ rotation fitted on ``y`` (Gong & Lazebnik, CVPR 2011: it spreads the
    variance over the bits, where the plain signs of decreasing-variance coordinates waste
    the last ones), then their signs (FAISS's ``IndexLSH`` without its own rotation)."""
    faiss = faiss_module()
    train = np.ascontiguousarray(y[:ITQ_TRAIN_ROWS, :bits], dtype=np.float32)
    itq = faiss.ITQMatrix(bits)
    itq.train(train)
    turn = faiss.LinearTransform(y.shape[1], bits, False)
    rot = faiss.vector_to_array(itq.A).reshape(bits, bits)
    a = np.zeros((bits, y.shape[1]), dtype=np.float32)
    a[:, :bits] = rot
    faiss.copy_array_to_vector(a.ravel(), turn.A)
    turn.is_trained = True
    return faiss.IndexPreTransform(turn, faiss.IndexLSH(bits, bits, False, False))


#: rows an ITQ rotation is fitted on (the first of the build's training rows)
ITQ_TRAIN_ROWS = 65_536


def _make(factory: str, x: np.ndarray, kind: MetricKind) -> Any:
    faiss = faiss_module()
    if projected_spec(factory) is not None:
        if kind != "l2":
            raise RuntimeError(f"{factory!r} searches L2 only")  # the caller's L2 proxy
        index = projected_scan(x, factory)
        index.add(np.ascontiguousarray(x, dtype=np.float32))
        return index
    try:
        index = faiss.index_factory(x.shape[1], factory, _faiss_metric(kind))
    except RuntimeError as exc:
        raise IndexBuildError(f"FAISS factory string {factory!r}: {_reason(exc)}") from None
    if not index.is_trained:
        try:
            index.train(x)
        except RuntimeError as exc:
            raise IndexBuildError(
                f"FAISS {factory!r} cannot be trained on {len(x)} references "
                f"({_reason(exc)}); use 'Flat' for small maps"
            ) from None
    index.add(x)
    index.search(x[:1], 1)  # some types cannot search some metrics (PQ with L1)
    return index


def _reason(exc: BaseException) -> str:
    """What a FAISS error says, without the C++ location FAISS puts before it."""
    lines = [s for s in str(exc).splitlines() if s.strip()]
    if not lines:
        return type(exc).__name__
    said = re.search(r"\.(?:cpp|h):\d+: (.*)$", lines[-1])
    return (said[1] if said else lines[-1])[:200]


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
        if metric.kind != "l1" and projected_spec(factory) is None:
            raise
        metric = MetricSpec("l2", 1.0, proxy=True)
        index = _make(factory, x, "l2")
    if params:
        set_search_params(index, params)
    return index, metric


#: the search parameter of a projected scan's ``G`` (the scan in front keeps ``G x F x k`` rows)
FRONT_FACTOR = "k_factor_front"


def set_search_params(index: Any, params: str) -> None:
    """Apply a FAISS ParameterSpace string (e.g. ``"nprobe=16"``, ``"efSearch=64"``).

    Items are separated by commas or spaces, as FAISS separates them. Also
    ``k_factor_front=G``: a projected scan's factor ``G`` of its scan in front (``S<e>``,
    ``FS<M>`` or ``B<b>``), set at build and changeable here. FAISS's ``k_factor_rf`` sets the outer
    ``IndexRefine``'s ``F`` only (its other names reach the indexes inside), so ``G``, the
    inner ``IndexRefine``'s factor, has this name of its own.
    """
    faiss = faiss_module()
    rest = []
    for item in filter(None, re.split(r"[\s,]+", params)):
        name, _, value = item.partition("=")
        if name == FRONT_FACTOR:
            _set_front_factor(index, value, params)
        else:
            rest.append(item)
    if not rest:
        return
    try:
        faiss.ParameterSpace().set_index_parameters(index, ",".join(rest))
    except RuntimeError as exc:
        raise IndexBuildError(f"FAISS search parameters {params!r}: {_reason(exc)}") from None


def _set_front_factor(index: Any, value: str, params: str) -> None:
    try:
        factor = float(value)
    except ValueError:
        factor = math.nan
    if not (math.isfinite(factor) and factor >= 1):
        raise IndexBuildError(
            f"FAISS search parameters {params!r}: {FRONT_FACTOR} needs a number >= 1, not {value!r}"
        )
    scan = _front_scan(index)
    if scan is None:
        raise IndexBuildError(
            f"FAISS search parameters {params!r}: {FRONT_FACTOR} needs a projected scan with "
            "a scan in front (S<e>, FS<M> or B<b>)"
        )
    scan.k_factor = factor


def _projected_parts(index: Any) -> tuple[Any, Any] | None:
    """A projected scan's outer ``IndexRefine`` (the re-ranking on ``D``) and what it
    re-ranks (its base, downcast), else None."""
    faiss = faiss_module()
    outer = faiss.downcast_index(index)
    if not isinstance(outer, faiss.IndexPreTransform):
        return None
    refine = faiss.downcast_index(outer.index)
    if not isinstance(refine, faiss.IndexRefine):
        return None
    return refine, faiss.downcast_index(refine.base_index)


def _front_scan(index: Any) -> Any | None:
    """The ``IndexRefine`` of a projected scan's scan in front and short scan, else None."""
    parts = _projected_parts(index)
    scan = None if parts is None else parts[1]
    return scan if isinstance(scan, faiss_module().IndexRefine) else None


def read_faiss(path: Path, params: str = "", *, mmap: bool = False) -> Any:
    """Load a FAISS index file (corruption -> :class:`IndexCorruptError` naming the file).

    ``mmap``: the codes of a flat-codes type (the projected scan's scalar codes, ``Flat``,
    ``SQ``, ``PQ``) are memory-mapped from the file instead of read into the process: they
    load at once, are shared by every replica on the machine through the page cache and
    are not the process's own memory. Such an index can be searched, not changed (a build
    reads without it); other types (IVF) are read into memory either way.
    """
    faiss = faiss_module()
    try:
        index = faiss.read_index(str(path), faiss.IO_FLAG_MMAP_IFC if mmap else 0)
    except RuntimeError as exc:
        raise IndexCorruptError(
            f"{path}: unreadable FAISS index ({_reason(exc)}); run `hmpf-index verify`"
        ) from None
    if params:
        set_search_params(index, params)
    return index


def search_faiss(index: Any, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``index.search(q, k)``, with what a projected scan's HNSW short list needs: a
    candidate list (``efSearch``) of at least the short list's ``F`` x ``k`` rows for this
    search (FAISS searches the graph with ``efSearch`` whatever ``k``, and would return
    fewer good rows than asked for). Passed per search (FAISS's search parameters), so the
    index is not changed and concurrent searches do not interfere."""
    found = _hnsw_short_list(index)
    if found is None:
        return index.search(q, k)
    faiss = faiss_module()
    refine, graph = found
    hnsw = faiss.SearchParametersHNSW()
    hnsw.efSearch = max(int(graph.hnsw.efSearch), math.ceil(k * refine.k_factor))
    short = faiss.SearchParametersPreTransform()
    short.index_params = hnsw
    ranked = faiss.IndexRefineSearchParameters()
    ranked.k_factor = refine.k_factor
    ranked.base_index_params = short
    outer = faiss.SearchParametersPreTransform()
    outer.index_params = ranked
    return index.search(q, k, params=outer)


def _hnsw_short_list(index: Any) -> tuple[Any, Any] | None:
    """A projected scan's ``IndexRefine`` and HNSW graph (``HNSW<M>``), else None."""
    faiss = faiss_module()
    parts = _projected_parts(index)
    if parts is None:
        return None
    refine, base = parts
    if not isinstance(base, faiss.IndexPreTransform):
        return None
    graph = faiss.downcast_index(base.index)
    return (refine, graph) if isinstance(graph, faiss.IndexHNSW) else None


def to_raw(values: np.ndarray, metric: MetricSpec) -> np.ndarray:
    """FAISS distances / similarities -> the method's raw scores (float64)."""
    v = np.asarray(values, dtype=np.float64)
    if metric.kind == "l2":
        v = np.sqrt(np.maximum(v, 0.0))
    return v * metric.scale
