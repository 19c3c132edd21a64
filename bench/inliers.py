"""Geometric verification (``inliers``) on top of the default hierarchy, Gardens Point.

    python bench/inliers.py [--json out.json] [--time-images 10]

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

import argparse
import json
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hmpf.config import HierarchyConfig, TierConfig, load_config  # noqa: E402
from hmpf.datasets import GARDENS_POINT_PROTOCOLS as PROTOCOLS  # noqa: E402
from hmpf.datasets import dataset_root  # noqa: E402
from hmpf.evaluation.calibrate import WEIGHT_LADDER, paired_test  # noqa: E402
from hmpf.evaluation.evaluate import EvalData, prepare  # noqa: E402
from hmpf.evaluation.study import ScoreBank, measure_query_ms, split_data  # noqa: E402
from hmpf.features import FeatureCache, default_cache_dir  # noqa: E402
from hmpf.index.storage import storage_dtype  # noqa: E402
from hmpf.methods import Method, create_method  # noqa: E402
from hmpf.runtime import machine_description  # noqa: E402

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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default=str(dataset_root()))
    ap.add_argument("--cache-dir", default=str(default_cache_dir()))
    ap.add_argument("--time-images", type=int, default=10)
    ap.add_argument("--json", help="write the figures here too")
    args = ap.parse_args()
    cache = FeatureCache(args.cache_dir)
    base = load_config("default")
    print(f"{machine_description()}", flush=True)
    banks: dict[tuple[str, str], ScoreBank] = {}
    pair_ms: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for proto, (r, q) in PROTOCOLS.items():
        data = EvalData.frames(Path(args.datasets) / r, Path(args.datasets) / q, 2)
        for part, split in zip(("train", "test"), split_data(data), strict=True):
            bank = ScoreBank.build(base, split, cache=cache)
            for v, ms in add_sparse(bank, base, cache).items():
                pair_ms[v].append(ms)
            banks[proto, part] = bank
            print(f"scored {proto} {part}", flush=True)

    def correct(config: HierarchyConfig, proto: str, part: str) -> np.ndarray:
        return np.asarray(banks[proto, part].run(config).correct, bool)

    # Model choice: each setting re-ranking the default's tier-1 candidates alone, and in the
    # final tier, on the training parts.
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
    print("\nms per scored pair: " + ", ".join(f"{v} {np.mean(t):.2f}" for v, t in pair_ms.items()))

    # (c): chosen on the training parts only.
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

    print("\n### Cost (ms per query end to end, one thread; bytes per reference)\n")
    print("| config | ms per query | extraction ms | hierarchy ms | bytes per reference |")
    print("|---|---|---|---|---|")
    first = next(iter(PROTOCOLS))
    for label, cfg in configs.items():
        bank = banks[first, "test"]
        t = measure_query_ms(cfg, bank, images=args.time_images, threads=1)
        size = bytes_per_reference(bank, cfg)
        rows[label].update(timing=t, bytes_per_reference=size)
        print(
            f"| {label} | {t['total_ms']:.1f} | {t['extract_ms']:.1f} | {t['hierarchy_ms']:.1f} "
            f"| {size:,.0f} |",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "machine": machine_description(),
                    "model_choice": choice_rows,
                    "pair_ms": {v: float(np.mean(t)) for v, t in pair_ms.items()},
                    "chosen": best,
                    "train_means": train,
                    "rows": rows,
                },
                indent=2,
                default=float,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
