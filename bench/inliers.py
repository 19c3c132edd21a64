"""Geometric verification (``inliers``) on top of the default hierarchy, Gardens Point.

    python -m bench.inliers [--json out.json] [--time-images 10]

Per Gardens Point protocol (``hmpf.datasets.GARDENS_POINT_PROTOCOLS``, +-2 frames, ``blocks``
split), on the training and the test part:

* (a) the default config (``load_config("default")``);
* (b) the default with ``inliers`` (its default settings) added to the final tier, and
  (b3) as a third tier re-ranking the default's top 3;
* (c) the variant chosen on the TRAINING parts only (mean recall@1 over the three protocols):
  an ``inliers`` setting (homography / fundamental matrix, threshold) in one of those two
  places, with the tier weights and the third tier's candidate count from the calibration's
  grid.

Scores come from :class:`~hmpf.evaluation.study.ScoreBank` (descriptor cache); ``inliers`` is
scored only on the candidates the default's tier 1 passes on (all any of these hierarchies
asks it for), as the service would. Test parts get a paired sign test against the default
(:func:`hmpf.evaluation.calibrate.paired_test`); ms per query is measured end to end on one
thread (:func:`hmpf.evaluation.study.measure_query_ms`, first test part); bytes per
reference are what an index stores (``exact`` precision).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from bench.harness import (
    add_data,
    add_json,
    machine,
    parser,
    split_parts,
    write_record,
)
from hmpf.config import HierarchyConfig, TierConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS as PROTOCOLS
from hmpf.evaluation.calibrate import WEIGHT_LADDER, paired_test
from hmpf.evaluation.evaluate import prepare
from hmpf.evaluation.study import ScoreBank, measure_query_ms
from hmpf.features import FeatureCache
from hmpf.index.storage import storage_dtype
from hmpf.methods import Method, create_method

#: ``inliers`` settings tried (method id -> parameters); "inliers" is the method's default.
VARIANTS: dict[str, dict[str, Any]] = {
    "inliers": {},
    "inl_h8": {"model": "homography", "ransac_threshold": 8.0},
    "inl_f1": {"model": "fundamental", "ransac_threshold": 1.0},
    "inl_f3": {"model": "fundamental", "ransac_threshold": 3.0},
}
TIER1 = ("gem", "netvlad")
TIER2 = ("olo", "gem", "netvlad", "gist")
K2 = (2, 3, 5)


def hierarchy(
    base: HierarchyConfig,
    name: str,
    tiers: list[tuple[tuple[str, ...], int]],
    weights: list[float],
) -> HierarchyConfig:
    """A hierarchy over the default's methods plus ``inliers`` variants."""
    used = {m for ms, _ in tiers for m in ms}
    methods = {m: dict(p) for m, p in base.methods.items() if m in used}
    for v in used & set(VARIANTS):
        methods[v] = {"type": "inliers", **VARIANTS[v]}
    return HierarchyConfig(
        name=name,
        mode=base.mode,
        tier_score=base.tier_score,
        methods=methods,
        tiers=[TierConfig(methods=list(ms), k=k) for ms, k in tiers],
        weights=weights,
    )


def candidates(base: HierarchyConfig, v: str) -> dict[str, HierarchyConfig]:
    """Every hierarchy (c) may be: ``v`` in the final tier, or as a third tier."""
    k1 = base.tiers[0].k
    out = {}
    for w in WEIGHT_LADDER:
        label = f"{v} in final tier [w {w:g}/1]"
        out[label] = hierarchy(base, label, [(TIER1, k1), ((*TIER2, v), 1)], [w, 1.0])
    for k2 in K2:
        for a in WEIGHT_LADDER:
            for b in WEIGHT_LADDER:
                if a > b:
                    continue
                label = f"{v} third tier on top {k2} [w {a:g}/{b:g}/1]"
                tiers = [(TIER1, k1), (TIER2, k2), ((v,), 1)]
                out[label] = hierarchy(base, label, tiers, [a, b, 1.0])
    return out


def add_sparse(bank: ScoreBank, base: HierarchyConfig, cache: FeatureCache) -> dict[str, float]:
    """Score every variant on the candidates the default's tier 1 passes on (NaN elsewhere)
    and add it to ``bank``; returns ms per scored pair per variant."""
    inputs = [r.tiers[1].inputs for r in bank.results(base)]
    methods: dict[str, Method] = {v: create_method("inliers", p) for v, p in VARIANTS.items()}
    # Every variant has the same features (one descriptor cache entry): extract them once.
    assert len({m.descriptor_key() for m in methods.values()}) == 1
    prep = prepare({"inliers": methods["inliers"]}, bank.data, cache=cache)
    db, qs = prep.db["inliers"], prep.queries["inliers"]
    per_pair = {}
    for v, m in methods.items():
        mat = np.full((bank.n_query, bank.n_db), np.nan)
        pairs, t0 = 0, time.perf_counter()
        for qi, (q, c) in enumerate(zip(qs, inputs, strict=True)):
            u = np.unique(np.asarray(c, np.int64))
            mat[qi, u] = m.scores(q, db, u)
            pairs += len(u)
        per_pair[v] = (time.perf_counter() - t0) * 1e3 / max(1, pairs)
        bank.methods[v], bank.scores[v], bank.features[v] = m, mat, (db, qs)
    return per_pair


def bytes_per_reference(
    bank: ScoreBank, config: HierarchyConfig, fixed: Mapping[str, float] | None = None
) -> float:
    """Mean bytes an index (``exact`` precision) stores per reference for ``config``
    (``fixed``: method id -> bytes per reference known otherwise, used as given)."""
    total = 0.0
    for mid in config.method_ids:
        if fixed is not None and mid in fixed:
            total += fixed[mid]
            continue
        m, db, n = bank.methods[mid], bank.features[mid][0], bank.n_db
        if m.kind == "global":
            a = np.asarray(db)
            total += a.size * storage_dtype(m, a, "exact").itemsize / n
            continue
        for i in range(n):
            for arr in m.to_arrays(db[i]).values():
                a = np.asarray(arr)
                total += (a.size * storage_dtype(m, a, "exact").itemsize + 8) / n
    return total


Correct = Callable[[HierarchyConfig, str, str], np.ndarray]
Banks = dict[tuple[str, str], ScoreBank]


def score(
    base: HierarchyConfig, datasets: str, cache: FeatureCache
) -> tuple[Banks, dict[str, list[float]]]:
    """Every protocol part's bank with the variants added; ms per scored pair per variant."""
    banks: Banks = {}
    pair_ms: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for proto in PROTOCOLS:
        for part, split in split_parts(proto, datasets):
            bank = ScoreBank.build(base, split, cache=cache)
            for v, ms in add_sparse(bank, base, cache).items():
                pair_ms[v].append(ms)
            banks[proto, part] = bank
            print(f"scored {proto} {part}", flush=True)
    return banks, pair_ms


def model_choice(base: HierarchyConfig, correct: Correct) -> dict[str, Any]:
    """Each setting re-ranking the default's tier-1 candidates alone, and in the final tier,
    on the training parts (printed)."""
    k1 = base.tiers[0].k
    print("\n### Model choice (training parts, recall@1)\n")
    print(
        "| setting | "
        + " | ".join(f"{p} alone | {p} +final" for p in PROTOCOLS)
        + " | mean +final |"
    )
    print("|---|" + "---|---|" * len(PROTOCOLS) + "---|")
    choice_rows = {}
    for v in VARIANTS:
        alone = hierarchy(base, "alone", [(TIER1, k1), ((v,), 1)], [0.5, 1.0])
        final = hierarchy(base, "final", [(TIER1, k1), ((*TIER2, v), 1)], [0.5, 1.0])
        cells, finals = [], []
        for p in PROTOCOLS:
            a, f = correct(alone, p, "train").mean(), correct(final, p, "train").mean()
            cells += [f"{a:.3f}", f"{f:.3f}"]
            finals.append(f)
        choice_rows[v] = {
            "params": VARIANTS[v],
            "cells": cells,
            "mean_final": float(np.mean(finals)),
        }
        print(
            f"| {v} {VARIANTS[v] or '(default)'} | "
            + " | ".join(cells)
            + f" | {np.mean(finals):.3f} |"
        )
    return choice_rows


def choose(
    base: HierarchyConfig, correct: Correct
) -> tuple[str, dict[str, float], dict[str, HierarchyConfig]]:
    """(c), chosen on the training parts only: its label, every candidate's mean training
    recall@1, and the configs compared ((a), (b), (b3), (c))."""
    k1 = base.tiers[0].k
    pool: dict[str, HierarchyConfig] = {}
    for v in VARIANTS:
        pool.update(candidates(base, v))
    train = {
        label: float(np.mean([correct(cfg, p, "train").mean() for p in PROTOCOLS]))
        for label, cfg in pool.items()
    }
    best = max(train, key=lambda lab: (train[lab], "third tier" in lab, lab))
    configs = {
        "(a) default": base,
        "(b) +inliers in final tier": hierarchy(
            base, "b", [(TIER1, k1), ((*TIER2, "inliers"), 1)], [0.5, 1.0]
        ),
        "(b3) +inliers third tier, top 3": hierarchy(
            base, "b3", [(TIER1, k1), (TIER2, 3), (("inliers",), 1)], [0.5, 0.75, 1.0]
        ),
        f"(c) {best}": pool[best],
    }
    print(f"\n(c) chosen on the training parts: {best} (mean train recall@1 {train[best]:.3f})")
    top = sorted(train, key=lambda lab: -train[lab])[:8]
    print("best training means: " + "; ".join(f"{lab} {train[lab]:.3f}" for lab in top))
    return best, train, configs


def recall_rows(
    configs: dict[str, HierarchyConfig], base: HierarchyConfig, correct: Correct
) -> dict[str, Any]:
    """Recall@1 of each config on every part; test parts signed against the default."""
    print("\n### Recall@1 (+-2 frames)\n")
    print("| config | " + " | ".join(f"{p} train | {p} test" for p in PROTOCOLS) + " | mean test |")
    print("|---|" + "---|---|" * len(PROTOCOLS) + "---|")
    rows: dict[str, Any] = {}
    for label, cfg in configs.items():
        cells, tests, signs = [], [], {}
        for p in PROTOCOLS:
            tr, te = correct(cfg, p, "train"), correct(cfg, p, "test")
            cells.append(f"{tr.mean():.3f}")
            t = paired_test(te, correct(base, p, "test"))
            signs[p] = t
            mark = (
                "" if label.startswith("(a)") else f" (+{t['wins']}/-{t['losses']}, p {t['p']:.2g})"
            )
            cells.append(f"{te.mean():.3f}{mark}")
            tests.append(te.mean())
        rows[label] = {"cells": cells, "mean_test": float(np.mean(tests)), "sign": signs}
        print(f"| {label} | " + " | ".join(cells) + f" | {np.mean(tests):.3f} |")
    return rows


def add_costs(
    rows: dict[str, Any], configs: dict[str, HierarchyConfig], bank: ScoreBank, images: int
) -> None:
    """Each config's ms per query (end to end, one thread) and bytes per reference."""
    print("\n### Cost (ms per query end to end, one thread; bytes per reference)\n")
    print("| config | ms per query | extraction ms | hierarchy ms | bytes per reference |")
    print("|---|---|---|---|---|")
    for label, cfg in configs.items():
        t = measure_query_ms(cfg, bank, images=images, threads=1)
        size = bytes_per_reference(bank, cfg)
        rows[label].update(timing=t, bytes_per_reference=size)
        print(
            f"| {label} | {t['total_ms']:.1f} | {t['extract_ms']:.1f} | {t['hierarchy_ms']:.1f} "
            f"| {size:,.0f} |",
            flush=True,
        )


def main() -> int:
    ap = parser(__doc__)
    add_data(ap)
    ap.add_argument("--time-images", type=int, default=10)
    add_json(ap)
    args = ap.parse_args()
    base = load_config("default")
    print(f"{machine()}", flush=True)
    banks, pair_ms = score(base, args.datasets, FeatureCache(args.cache_dir))

    def correct(config: HierarchyConfig, proto: str, part: str) -> np.ndarray:
        return np.asarray(banks[proto, part].run(config).correct, bool)

    choice_rows = model_choice(base, correct)
    print("\nms per scored pair: " + ", ".join(f"{v} {np.mean(t):.2f}" for v, t in pair_ms.items()))
    best, train, configs = choose(base, correct)
    rows = recall_rows(configs, base, correct)
    add_costs(rows, configs, banks[next(iter(PROTOCOLS)), "test"], args.time_images)
    if args.json:
        results = {
            "model_choice": choice_rows,
            "pair_ms": {v: float(np.mean(t)) for v, t in pair_ms.items()},
            "chosen": best,
            "train_means": train,
            "rows": rows,
        }
        write_record(args.json, results, args, config=base, default=float)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
