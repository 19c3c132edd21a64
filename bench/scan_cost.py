"""What one scan of every row costs a tier-1 query, per code type, on one thread.

    python -m bench.scan_cost --json docs/experiments/scale/scan_cost.json

The projected scan (``PCA<D>:<d>,<codes>``, :func:`hmpf.index.ann.projected_scan`) looks at
every reference on its first ``d`` dimensions for each query; at a million references that
scan is most of what tier 1 adds to a query (docs/scale.md). This bench times the scan alone
for the code types FAISS offers on flat codes, over ``--rows`` rows, keeping the ``--k``
nearest (the projected scan keeps ``F x 256`` = 2048 by default): scalar codes of ``d``
dimensions (``SQfp16``, what the scale bench's million-reference versions use; ``SQ8``) and
binary codes of ``b`` bits (``IndexBinaryFlat``, Hamming distance: a candidate lever, not a
type hmpf builds). The types take turns on each round (``--rounds``), one query at a time,
median over every query and round.

Times only: the rows are random (a scan reads every row whatever its values), so the record
says nothing about which neighbours a type keeps; that needs real descriptors
(``bench.tier1_real``, ``bench.scale factories``).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np

from bench.harness import add_json, parser, write_record
from hmpf.index.ann import faiss_module

#: (name, kind, size): scalar codes of ``size`` dimensions or binary codes of ``size`` bits.
TYPES = (
    ("SQfp16 d=64", "QT_fp16", 64),
    ("SQ8 d=64", "QT_8bit", 64),
    ("SQfp16 d=128", "QT_fp16", 128),
    ("SQ8 d=128", "QT_8bit", 128),
    ("binary 128 bits", "binary", 128),
    ("binary 256 bits", "binary", 256),
)


def bytes_per_row(kind: str, size: int) -> int:
    """Bytes a row's code takes: ``size`` bits, or ``size`` dimensions of 2 (float16) or 1."""
    return size // 8 if kind == "binary" else size * (2 if kind == "QT_fp16" else 1)


def build(kind: str, size: int, rows: int, rng: np.random.Generator) -> tuple[Any, np.ndarray]:
    """A filled flat index of ``rows`` random rows, and 64 queries near stored rows (as a
    real query is near its place)."""
    faiss = faiss_module()
    if kind == "binary":
        codes = rng.integers(0, 256, (rows, size // 8), dtype=np.uint8)
        index = faiss.IndexBinaryFlat(size)
        index.add(codes)
        return index, codes[rng.integers(0, rows, 64)]
    # a decaying spectrum, as principal-component coordinates have
    x = rng.standard_normal((rows, size), dtype=np.float32)
    x /= np.sqrt(1.0 + np.arange(size, dtype=np.float32))
    index = faiss.IndexScalarQuantizer(size, getattr(faiss.ScalarQuantizer, kind))
    index.train(x[: min(rows, 65536)])
    index.add(x)
    return index, x[rng.integers(0, rows, 64)] + 0.01


def main(argv: list[str] | None = None) -> None:
    ap = parser(__doc__)
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--k", type=int, default=2048, help="nearest rows kept per query")
    ap.add_argument("--queries", type=int, default=20, help="queries per type and round")
    ap.add_argument("--rounds", type=int, default=3)
    add_json(ap)
    a = ap.parse_args(argv)
    faiss = faiss_module()
    faiss.omp_set_num_threads(1)
    rng = np.random.default_rng(0)
    indexes = {name: build(kind, size, a.rows, rng) for name, kind, size in TYPES}
    times: dict[str, list[float]] = {name: [] for name in indexes}
    for _ in range(a.rounds):
        for name, (index, queries) in indexes.items():
            index.search(queries[:1], a.k)  # warm-up
            for q in queries[: a.queries]:
                t = time.perf_counter()
                index.search(q[None, :], a.k)
                times[name].append((time.perf_counter() - t) * 1e3)
    base = statistics.median(times["SQfp16 d=128"])
    print(f"{a.rows:,} rows, top {a.k}, one thread ({a.rounds} rounds x {a.queries} queries)")
    print(f"{'codes':18s} {'bytes/row':>9s} {'ms p50':>8s} {'vs SQfp16 d=128':>16s}")
    out = {}
    for name, kind, size in TYPES:
        p50 = statistics.median(times[name])
        nbytes = bytes_per_row(kind, size)
        out[name] = {"bytes_per_row": nbytes, "ms_p50": p50, "ms": times[name]}
        print(f"{name:18s} {nbytes:9d} {p50:8.2f} {base / p50:15.2f}x")
    if a.json:
        results = {"rows": a.rows, "k": a.k, "types": out}
        print("wrote", write_record(a.json, results, a))


if __name__ == "__main__":
    main()
