"""Tier-1 FAISS choice on real descriptors: exact Flat against IVF, as far as real data goes.

    .venv/bin/python -m bench.tier1_real [--methods gem netvlad] [--winter-every 4] [--json F]

``bench/index_search.py`` sizes tier 1 on synthetic route-like vectors up to a million
references. This checks the same choice on the real descriptors we have: one map made of
every reference route in ``$HMPF_DATASETS`` (Nordland summer, 3576 frames, and Gardens Point
day_left and day_right, 200 each: 3976 references of three routes and two kinds of camera),
queried by Nordland winter (every ``--winter-every``-th frame) and Gardens Point night_right.

Per tier-1 method of the default config (descriptors from the descriptor cache; a method
that needs fitting is fitted on the whole mixed map), per FAISS type (``Flat``; ``IVF{n},Flat``
and ``IVF{n},PQ{m}`` for n = sqrt(R), 4 sqrt(R), m = D / 20 sub-quantizers of 8 bits) and
``nprobe``, it prints the bytes per reference the FAISS index holds in memory and:

* ``exact top-k kept``: the fraction of the exact top-k (k = the default's tier-1 k = 10)
  that the reader's approximate path (FAISS's top max(256, 4k) plus its 1024-reference
  sample, re-scored exactly) keeps: where all are kept, tier 1 passes on the same list. In
  brackets: without the sample, which is a quarter of this small map but 0.1 % of a
  million-reference one (the figure that carries over to large maps);
* ``right kept``: of the queries whose exact top-k holds a right place (+-2 frames, on its
  own route), the fraction whose approximate list still holds one;
* single-query FAISS search time p50 (one thread; re-scoring not included).

``--json F`` writes the same figures as a JSON record (provenance, then per method its exact
search's figures and one row per FAISS type and setting).

Nothing is chosen on these routes' test parts: this only says whether the IVF settings the
capacity model (docs/scale.md) recommends lose tier-1 candidates on real descriptors.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import add_config, add_json, machine, parser, write_record
from hmpf.config import build_methods, load_config
from hmpf.datasets import dataset_root, list_images
from hmpf.features import FeatureCache, default_cache_dir, extract_images, fit_methods
from hmpf.index.ann import build_faiss, declared_metric, faiss_module, set_search_params
from hmpf.index.reader import SAMPLE_SIZE

TOLERANCE = 2


def routes(root: Path, winter_every: int) -> tuple[list[Path], np.ndarray, list[Path], np.ndarray]:
    """Reference and query paths with (route, frame) labels for ground truth."""
    refs: list[Path] = []
    ref_lab: list[tuple[int, int]] = []
    qs: list[Path] = []
    q_lab: list[tuple[int, int]] = []
    nl = root / "nordland_64x32"
    gp = root / "gardens_point"
    # Gardens Point's day_left and day_right are frame-aligned traverses of the same places:
    # one place-route (1), so a night query's right answer may sit on either
    for rid, folder in [(0, nl / "summer"), (1, gp / "day_left"), (1, gp / "day_right")]:
        paths = list_images(folder)
        refs += paths
        ref_lab += [(rid, i) for i in range(len(paths))]
    winter = list_images(nl / "winter")
    pick = range(0, len(winter), winter_every)
    qs += [winter[i] for i in pick]
    q_lab += [(0, i) for i in pick]
    night = list_images(gp / "night_right")
    qs += night
    q_lab += [(1, i) for i in range(len(night))]  # frame-aligned with both day traverses
    return refs, np.array(ref_lab), qs, np.array(q_lab)


def right_mask(ref_lab: np.ndarray, q_lab: np.ndarray) -> np.ndarray:
    """(Q, R) True where reference r is a right answer for query q."""
    same_route = q_lab[:, None, 0] == ref_lab[None, :, 0]
    close = np.abs(q_lab[:, None, 1] - ref_lab[None, :, 1]) <= TOLERANCE
    return same_route & close


def pq_subquantizers(d: int) -> int:
    """PQ sub-quantizers: about 20 dimensions each (a divisor of ``d``), 8 bits each."""
    m = max(1, d // 20)
    while d % m:
        m -= 1
    return m


def search_times(index: object, q: np.ndarray, k: int) -> float:
    """Median ms of single-query searches (one thread)."""
    times = []
    for row in q[:200]:
        t0 = time.perf_counter()
        index.search(row[None, :], k)  # type: ignore[attr-defined]
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def kept(
    cand: np.ndarray,
    extra: np.ndarray,
    rank: np.ndarray,
    top_exact: np.ndarray,
    right: np.ndarray,
    held: np.ndarray,
    k: int,
) -> tuple[float, float]:
    """The reader's approximate path on FAISS candidates ``cand`` (plus ``extra`` scored
    exactly): the share of the exact top k kept, and of the right places the exact top k
    held, kept."""
    kept_top = np.empty(len(cand))
    kept_right = np.empty(len(cand), bool)
    for i, c in enumerate(cand):
        scored = np.union1d(c[c >= 0], extra)
        top = scored[np.argsort(rank[i, scored], kind="stable")[:k]]
        kept_top[i] = np.isin(top_exact[i], top).mean()
        kept_right[i] = right[i, top].any()
    return float(kept_top.mean()), float((kept_right & held).sum() / max(int(held.sum()), 1))


def report_method(
    mid: str,
    x: np.ndarray,
    q: np.ndarray,
    metric: Any,
    right: np.ndarray,
    k: int,
    nprobes: list[int],
    others: list[str] = [],  # noqa: B006 - read only
) -> dict[str, Any]:
    """One tier-1 method: exact search's figures, then each IVF index's and each of
    ``others`` (``FACTORY|SETTING;SETTING``): printed, and returned as the JSON record's
    entry."""
    faiss = faiss_module()
    n = len(x)
    exact, _ = build_faiss(x, metric, "Flat")
    _, order = exact.search(q, n)  # every reference, best first
    top_exact = order[:, :k]
    rank = np.empty_like(order)
    rank[np.arange(len(q))[:, None], order] = np.arange(n)[None, :]
    held = right[np.arange(len(q))[:, None], top_exact].any(axis=1)
    r1_exact = right[np.arange(len(q)), top_exact[:, 0]].mean()
    flat_ms = search_times(exact, q, k)
    print(
        f"\n{mid} ({x.shape[1]}-d, metric {metric.kind}): exact top-{k} holds the right "
        f"place for {held.mean():.3f} of queries, recall@1 {r1_exact:.3f}, "
        f"Flat p50 {flat_ms:.2f} ms"
    )
    out: dict[str, Any] = {
        "dim": int(x.shape[1]),
        "metric": metric.kind,
        "references": n,
        "queries": len(q),
        "right_in_exact_top_k": float(held.mean()),
        "recall_at_1_exact": float(r1_exact),
        "flat_p50_ms": flat_ms,
        "approx_k": max(256, 4 * k),
        "sample": min(n, SAMPLE_SIZE),
        "rows": [],
    }
    # the reader's approximate path (hmpf.index.reader): FAISS's top max(256, 4k) and an
    # evenly spaced sample of up to 1024 references are scored exactly, the rest get the
    # worst value; tier 1 then keeps the exact top k of those
    approx_k = max(256, 4 * k)
    sample = np.unique(np.linspace(0, n - 1, min(n, SAMPLE_SIZE)).round().astype(np.int64))
    print(
        f"| FAISS | bytes/ref in RAM | nprobe | exact top-{k} kept (no sample) "
        "| right kept (no sample) | p50 ms (FAISS only) |"
    )
    print("|---|---:|---:|---|---|---:|")

    def print_row(factory: str, ram: float, setting: str, index: Any) -> None:
        """One table row: ``index``'s candidates through the reader's path, with and
        without the sample."""
        _, cand = index.search(q, approx_k)
        ks = kept(cand, sample, rank, top_exact, right, held, k)
        kn = kept(cand, np.zeros(0, np.int64), rank, top_exact, right, held, k)
        ms = search_times(index, q, approx_k)
        print(
            f"| {factory} | {ram:.0f} | {setting} | {ks[0]:.4f} ({kn[0]:.4f}) "
            f"| {ks[1]:.4f} ({kn[1]:.4f}) | {ms:.2f} |"
        )
        out["rows"].append(
            {
                "factory": factory,
                "bytes_per_reference": ram,
                "setting": setting,
                "exact_top_k_kept": ks[0],
                "exact_top_k_kept_no_sample": kn[0],
                "right_kept": ks[1],
                "right_kept_no_sample": kn[1],
                "faiss_p50_ms": ms,
            }
        )

    s1, s4 = int(round(np.sqrt(n))), int(round(4 * np.sqrt(n)))
    pq = pq_subquantizers(x.shape[1])
    for factory in (f"IVF{s1},Flat", f"IVF{s4},Flat", f"IVF{s1},PQ{pq}", f"IVF{s4},PQ{pq}"):
        ivf, _ = build_faiss(x, metric, factory)
        ram = len(faiss.serialize_index(ivf)) / n
        for nprobe in nprobes:
            if nprobe > int(ivf.nlist):
                continue
            ivf.nprobe = nprobe
            print_row(factory, ram, str(nprobe), ivf)
    for spec in others:  # other types, each with its search settings ("FACTORY|a=1;a=2")
        factory, _, settings = spec.partition("|")
        index, _ = build_faiss(x, metric, factory)
        ram = len(faiss.serialize_index(index)) / n
        for setting in settings.split(";") if settings else [""]:
            if setting:
                set_search_params(index, setting)
            print_row(factory, ram, setting or "-", index)
    return out


def main() -> None:
    p = parser(__doc__)
    add_config(p)
    p.add_argument("--methods", nargs="*", default=None, help="default: the config's tier 1")
    p.add_argument("--winter-every", type=int, default=4)
    p.add_argument("--k", type=int, default=None, help="default: the config's tier-1 k")
    p.add_argument("--nprobe", type=int, nargs="*", default=[1, 2, 4, 8, 16, 32])
    p.add_argument("--workers", type=int, default=None)
    p.add_argument(
        "--factory",
        action="append",
        default=[],
        metavar="[METHOD=]FACTORY[|SETTING;...]",
        help="another FAISS type to measure, e.g. 'netvlad=PCA1024:128,SQfp16|k_factor_rf=1'",
    )
    add_json(p)
    a = p.parse_args()
    faiss_module().omp_set_num_threads(1)
    config = load_config(a.config)
    k = a.k or config.tiers[0].k
    tier1 = a.methods or list(config.tiers[0].methods)
    methods = {mid: m for mid, m in build_methods(config).items() if mid in tier1}
    refs, ref_lab, qs, q_lab = routes(dataset_root(), a.winter_every)
    print(machine())
    print(f"map: {len(refs)} references (3 routes), {len(qs)} queries; tier-1 k = {k}")
    cache = FeatureCache(default_cache_dir())
    fit_methods(methods, refs, cache=cache)
    r_feat = extract_images(refs, methods, cache=cache, workers=a.workers, progress=True)
    q_feat = extract_images(qs, methods, cache=cache, workers=a.workers, progress=True)
    right = right_mask(ref_lab, q_lab)
    results: dict[str, Any] = {
        "references": len(refs),
        "queries": len(qs),
        "k": k,
        "winter_every": a.winter_every,
        "methods": {},
    }
    for mid, m in methods.items():
        metric = declared_metric(mid, m)
        if metric is None:
            print(f"{mid}: no FAISS metric, tier 1 scans the matrix")
            continue
        x = np.ascontiguousarray(m.stack(r_feat.features[mid]), np.float32)
        q = np.ascontiguousarray(m.stack(q_feat.features[mid]), np.float32)
        others = [f.partition("=")[2] if f.startswith(f"{mid}=") else f for f in a.factory]
        others = [f for f in others if "=" not in f.partition("|")[0]]  # another method's
        results["methods"][mid] = report_method(mid, x, q, metric, right, k, a.nprobe, others)
    print(f"\nload {os.getloadavg()[0]:.2f}")
    if a.json:
        results["load_1min_after"] = os.getloadavg()[0]
        print(f"report: {write_record(a.json, results, a, preset=str(a.config))}")


if __name__ == "__main__":
    main()
