"""Tier-1 search latency against map size: exact FAISS Flat vs IVF, synthetic descriptors.

    .venv/bin/python -m bench.index_search --sizes 10000 100000 1000000 [--json F]

Descriptors model a fleet's map: unit 512-d float32 vectors along routes. Each route is a
smooth random walk in a 64-d latent space (consecutive frames look alike, distant places do
not), projected to 512-d with per-frame noise, so a query's true neighbours are the frames
around its place, as with real place descriptors. Queries are another traverse: the latent
point of a random reference frame, re-noised. Prints per size: build time, p50 / p95
single-query latency (k=100), recall@100 of IVF against exact search, the nprobe chosen (the
smallest reaching the target), and the cost of the reader's exact re-scoring of the
approximate candidates; with ``--json`` writes them too.
"""

from __future__ import annotations

import time
from typing import Any

import faiss
import numpy as np

from bench.harness import add_json, parser, write_record
from hmpf.methods.base import euclidean

ROUTE_FRAMES = 2000  # frames per route: 10k references are 5 routes, 1M are 500


def routes(
    n: int, d: int, rng: np.random.Generator, proj: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(n, d) unit reference descriptors along routes, and their (n, latent) positions."""
    latent = np.empty((n, proj.shape[0]), np.float32)
    for s in range(0, n, ROUTE_FRAMES):
        m = min(ROUTE_FRAMES, n - s)
        start = 3.0 * rng.standard_normal(proj.shape[0])
        steps = 0.15 * rng.standard_normal((m, proj.shape[0]))
        latent[s : s + m] = start + np.cumsum(steps, axis=0)
    return describe(latent, rng, proj), latent


def describe(latent: np.ndarray, rng: np.random.Generator, proj: np.ndarray) -> np.ndarray:
    out = np.empty((len(latent), proj.shape[1]), np.float32)
    for s in range(0, len(latent), 100_000):
        x = latent[s : s + 100_000] @ proj
        x += 0.5 * rng.standard_normal(x.shape, dtype=np.float32)
        out[s : s + 100_000] = x / np.linalg.norm(x, axis=1, keepdims=True)
    return out


def latencies(index: faiss.Index, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    ids = np.empty((len(q), k), np.int64)
    ts = np.empty(len(q))
    for i in range(len(q)):
        t = time.perf_counter()
        _, ids[i] = index.search(q[i : i + 1], k)
        ts[i] = (time.perf_counter() - t) * 1e3
    return ts, ids


def recall(approx: np.ndarray, exact: np.ndarray) -> float:
    return float(
        np.mean([len(set(a) & set(e)) / len(e) for a, e in zip(approx, exact, strict=True)])
    )


def main() -> None:
    p = parser(__doc__)
    p.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    p.add_argument("--dim", type=int, default=512)
    p.add_argument("--queries", type=int, default=200)
    p.add_argument("--k", type=int, default=100)
    p.add_argument("--target", type=float, default=0.95)
    add_json(p)
    a = p.parse_args()
    rng = np.random.default_rng(0)
    proj = (rng.standard_normal((64, a.dim)) / 8.0).astype(np.float32)
    print(
        f"faiss {faiss.__version__}, threads {faiss.omp_get_max_threads()}, d={a.dim}, "
        f"k={a.k}, {a.queries} single queries"
    )
    sizes: list[dict[str, Any]] = []
    for n in a.sizes:
        x, latent = routes(n, a.dim, rng, proj)
        q = describe(latent[rng.integers(0, n, a.queries)], rng, proj)
        t = time.perf_counter()
        flat = faiss.IndexFlatL2(a.dim)
        flat.add(x)
        flat_build = time.perf_counter() - t
        ts, exact = latencies(flat, q, a.k)
        flat_row = {
            "build_s": flat_build,
            "p50_ms": float(np.percentile(ts, 50)),
            "p95_ms": float(np.percentile(ts, 95)),
            "bytes_per_ref": flat.ntotal * a.dim * 4 / n,
        }
        print(
            f"N={n:>8}  Flat      build {flat_build:6.1f} s  p50 {flat_row['p50_ms']:7.2f} ms"
            f"  p95 {flat_row['p95_ms']:7.2f} ms  recall@{a.k} 1.000  "
            f"mem {flat_row['bytes_per_ref']:.0f} B/ref"
        )
        nlist = int(4 * np.sqrt(n))
        t = time.perf_counter()
        ivf = faiss.index_factory(a.dim, f"IVF{nlist},Flat")
        train = x[rng.choice(n, min(n, 64 * nlist), replace=False)]
        ivf.train(train)
        ivf.add(x)
        ivf_build = time.perf_counter() - t
        for nprobe in (4, 8, 16, 32, 64, 128):
            ivf.nprobe = nprobe
            ts, ids = latencies(ivf, q, a.k)
            r = recall(ids, exact)
            if r >= a.target or nprobe == 128:
                break
        ivf_row = {
            "factory": f"IVF{nlist},Flat",
            "nlist": nlist,
            "nprobe": nprobe,
            "build_s": ivf_build,
            "p50_ms": float(np.percentile(ts, 50)),
            "p95_ms": float(np.percentile(ts, 95)),
            "recall": r,
        }
        print(
            f"N={n:>8}  IVF{nlist},Flat nprobe={nprobe}  build {ivf_build:6.1f} s  "
            f"p50 {ivf_row['p50_ms']:7.2f} ms  p95 {ivf_row['p95_ms']:7.2f} ms  "
            f"recall@{a.k} {r:.3f}"
        )
        rows = x[: 256 + 1024]
        t = time.perf_counter()
        for i in range(20):
            euclidean(q[i : i + 1], rows)
        rescore_ms = (time.perf_counter() - t) / 20 * 1e3
        print(
            f"N={n:>8}  reader re-scoring of 256 candidates + 1024 sample: "
            f"{rescore_ms:.2f} ms/query"
        )
        del flat, ivf, x
        sizes.append({"n": n, "flat": flat_row, "ivf": ivf_row, "rescore_ms": rescore_ms})
    if a.json:
        results = {
            "faiss": faiss.__version__,
            "threads": int(faiss.omp_get_max_threads()),
            "dim": a.dim,
            "k": a.k,
            "queries": a.queries,
            "target": a.target,
            "sizes": sizes,
        }
        print(f"report: {write_record(a.json, results, a)}")


if __name__ == "__main__":
    main()
