"""How a non-final tier enters the Combined score: the original's max against the mean.

    python -m bench.tier_score [--hierarchies 600] [--seed 0] [--json out.json]

Per Gardens Point protocol (``hmpf.datasets.GARDENS_POINT_PROTOCOLS``, ``blocks`` split,
+-2 frames), draws ``--hierarchies`` random 2- and 3-tier hierarchies of the calibration pool
(1-2 methods per tier, candidate counts and weights from the calibration grid), runs each with
``tier_score: max`` and ``tier_score: mean`` on the training and the test part, and prints the
mean recall@1 of both and how often the mean is better or worse. Same seed, same hierarchies.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bench.harness import (
    ROOT,
    add_data,
    add_json,
    machine,
    parser,
    protocol_data,
    write_record,
)
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS as PROTOCOLS
from hmpf.evaluation.calibrate import WEIGHT_LADDER, SearchSpace, describe
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import ScoreBank, derive_config, split_data
from hmpf.features import FeatureCache

Hierarchy = tuple[list[tuple[tuple[str, ...], int]], list[float]]


def draw(space: SearchSpace, n: int, seed: int) -> list[Hierarchy]:
    """``n`` distinct random hierarchies: (tiers as (methods, k), weights)."""
    rng = np.random.default_rng(seed)
    sets = space.tier_sets()
    out: dict[str, Hierarchy] = {}
    while len(out) < n:
        n_tiers = int(rng.integers(2, 4))
        tiers = [sets[int(i)] for i in rng.integers(0, len(sets), n_tiers)]
        k1 = int(rng.choice(space.k1))
        ks = [k1, 1] if n_tiers == 2 else [k1, int(rng.choice([k for k in space.k2 if k < k1])), 1]
        ladder = sorted(float(w) for w in rng.choice(WEIGHT_LADDER, n_tiers - 1))
        weights = [*ladder, 1.0]
        out.setdefault(describe(tiers, ks, weights), (list(zip(tiers, ks, strict=True)), weights))
    return list(out.values())


def compare(
    pool: HierarchyConfig, split: EvalData, hierarchies: list[Hierarchy], cache: FeatureCache
) -> dict[str, Any]:
    """Mean recall@1 of ``hierarchies`` on ``split`` with either tier score, and how often
    the mean is better or worse."""
    bank = ScoreBank.build(pool, split, cache=cache)
    rec = {
        ts: np.array(
            [
                bank.run(
                    derive_config(pool.model_copy(update={"tier_score": ts}), tiers, ws)
                ).recall_at_1
                for tiers, ws in hierarchies
            ]
        )
        for ts in ("max", "mean")
    }
    d = rec["mean"] - rec["max"]
    return {
        "max": float(rec["max"].mean()),
        "mean": float(rec["mean"].mean()),
        "difference": float(d.mean()),
        "mean_better": float(np.mean(d > 0)),
        "mean_worse": float(np.mean(d < 0)),
    }


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--hierarchies", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    add_data(ap)
    add_json(ap)
    ap.smoke(hierarchies=10)
    args = ap.parse_args()
    cache = FeatureCache(args.cache_dir)
    pool = load_config(ROOT / "configs" / "calibration-pool.yaml")
    hierarchies = draw(SearchSpace(tuple(pool.method_ids)), args.hierarchies, args.seed)
    print(f"{machine()}; {len(hierarchies)} hierarchies, seed {args.seed}")
    print(
        "| protocol | part | mean R@1, max | mean R@1, mean | difference | mean better "
        "| mean worse |"
    )
    print("|---|---|---|---|---|---|---|")
    rows = []
    for proto in PROTOCOLS:
        data = protocol_data(proto, args.datasets)
        for part, split in zip(("train", "test"), split_data(data), strict=True):
            row = {"protocol": proto, "part": part, **compare(pool, split, hierarchies, cache)}
            rows.append(row)
            print(
                f"| {proto} | {part} | {row['max']:.3f} | {row['mean']:.3f} | "
                f"{row['difference']:+.3f} | {row['mean_better']:.0%} | {row['mean_worse']:.0%} |",
                flush=True,
            )
    if args.json:
        write_record(args.json, {"rows": rows}, args, config=pool)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
