"""Places that are not in the map: how often are queries from elsewhere accepted?

    python bench/out_of_map.py [--nordland 200] [--out results/out_of_map.json]

Each map is the *training part* of a Gardens Point night protocol (``gp_dr_nr``: day_right
references, ``gp_dl_nr``: day_left), split as ``hmpf-calibrate`` splits it (alternating
stretches of 20 frames), with the default hierarchy. On that training part, as
``hmpf-calibrate --sequence`` does (:mod:`hmpf.evaluation.acceptance`): the single-frame
confidence model and its threshold for 99 % precision (out-of-fold), the z threshold
(Combined z, lowest value giving 99 % on the training answers); the sequence model on the
training drives (speeds 1, 2, 3) with the default :class:`~hmpf.sequence.FilterParams`, its
threshold, and the posterior-mass threshold chosen the same way as the z threshold.

Then two sets of queries the map does not cover, each answered against the map:

* ``nordland``: ``--nordland`` Nordland winter frames spread evenly over the traverse
  (64x32 thumbnails through the same extraction);
* ``gp_night_removed``: the protocol's test-part night queries against the training part's
  references, i.e. the map with the queries' own references removed. Queries whose
  +-2-frame ground truth still reaches a training reference (the two frames either side of
  each join of the 20-frame stretches) are left out: for them the place *is* in the map.

Single frame: each answer accepted by the model (``p_correct >= threshold``) or by the z
rule. Sequence mode: the queries driven in order as one vehicle through the filter (every
frame counts; the Nordland frames are ~18 frames apart, a vehicle far faster than the map's
route), accepted by the sequence model or by the posterior mass. A false accept is an
accepted answer to an out-of-map query; the goal of issue 17 is <= 1 %.

Writes the JSON report and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hmpf.confidence import ConfidenceModel, feature_matrix  # noqa: E402
from hmpf.config import load_config  # noqa: E402
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root, list_images  # noqa: E402
from hmpf.evaluation.acceptance import (  # noqa: E402
    SEQUENCE_MODEL_FEATURES,
    SINGLE_FEATURES,
    Answers,
    fit_acceptance,
    sequence_answers,
    single_answers,
)
from hmpf.evaluation.calibrate import acceptance_threshold  # noqa: E402
from hmpf.evaluation.evaluate import EvalData  # noqa: E402
from hmpf.evaluation.sequence import training_drives  # noqa: E402
from hmpf.evaluation.study import ScoreBank, split_data  # noqa: E402
from hmpf.features import FeatureCache, default_cache_dir  # noqa: E402
from hmpf.runtime import machine_description  # noqa: E402
from hmpf.sequence import FilterParams, RouteMap  # noqa: E402

MAPS = ("gp_dr_nr", "gp_dl_nr")
TARGET = 0.99
GOAL = 0.01
TOLERANCE = 2
BLOCK = 20


# -- pure helpers -------------------------------------------------------------------------------


def spread(n: int, count: int) -> np.ndarray:
    """``count`` indices spread evenly over ``range(n)`` (all of them when ``count >= n``)."""
    if count >= n:
        return np.arange(n)
    if count < 1:
        raise ValueError("count must be >= 1")
    return np.unique(np.linspace(0, n - 1, count).round().astype(np.int64))


def block_parts(n: int, block: int = BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the training and test parts of the blocks split (as ``split_data``)."""
    blk = (np.arange(n) // block) % 2
    return np.flatnonzero(blk == 0), np.flatnonzero(blk == 1)


def out_of_map(full_gt: np.ndarray, queries: np.ndarray, map_refs: np.ndarray) -> np.ndarray:
    """(len(queries),) True where no ground-truth reference of the query is in the map."""
    gt = np.asarray(full_gt, dtype=bool)
    return ~gt[np.ix_(np.asarray(queries), np.asarray(map_refs))].any(axis=1)


def false_accepts(accepted: np.ndarray, outside: np.ndarray) -> dict[str, Any]:
    """Accepted answers among the out-of-map queries: count, share, and the one-sided 95 %
    upper bound on the rate (Clopper-Pearson; what the count can rule out)."""
    from scipy.stats import beta

    a = np.asarray(accepted, dtype=bool)
    o = np.asarray(outside, dtype=bool)
    if a.shape != o.shape:
        raise ValueError("accepted and outside must have the same shape")
    n, k = int(o.sum()), int((a & o).sum())
    upper = float(beta.ppf(0.95, k + 1, n - k)) if n and k < n else 1.0
    return {
        "n": n,
        "false_accepts": k,
        "rate": k / n if n else None,
        "upper_95": upper,
        "met": (k / n <= GOAL) if n else None,
    }


def table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of the report's rows."""
    lines = [
        "| map | out-of-map queries | mode | rule | threshold | false accepts | rate "
        "(95 % upper bound) | goal <= 1 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        fa = r["result"]
        rate = "n/a" if fa["rate"] is None else f"{fa['rate']:.3f}"
        met = "n/a" if fa["met"] is None else ("yes" if fa["met"] else "no")
        lines.append(
            f"| {r['map']} | {r['queries']} ({fa['n']}) | {r['mode']} | {r['rule']} | "
            f"{r['threshold']:.4g} | {fa['false_accepts']} | {rate} ({fa['upper_95']:.3f}) "
            f"| {met} |"
        )
    return "\n".join(lines)


# -- the map's acceptance, chosen on its training part -------------------------------------------


def fit_map(train: ScoreBank, config: Any, params: FilterParams) -> dict[str, Any]:
    """Models and thresholds of one map, on its training part (as ``hmpf-calibrate``)."""
    routes = RouteMap.from_metadata(train.n_db)
    results = train.results(config)
    single = single_answers(results, train.gt, routes)
    model, thr, figs = fit_acceptance(single, SINGLE_FEATURES, TARGET)
    z = acceptance_threshold(single.score, single.correct, TARGET)
    seq = sequence_answers(results, train.gt, routes, params, training_drives(train.n_query))
    smodel, sthr, sfigs = fit_acceptance(seq, SEQUENCE_MODEL_FEATURES, TARGET)
    mass = acceptance_threshold(seq.score, seq.correct, TARGET)
    return {
        "model": model,
        "threshold": thr,
        "z": z["threshold"],
        "sequence_model": smodel,
        "sequence_threshold": sthr,
        "mass": mass["threshold"],
        "train": {"single": figs, "sequence": sfigs, "z": z, "mass": mass},
    }


def decisions(
    fitted: dict[str, Any], single: Answers, seq: Answers
) -> list[tuple[str, str, float, np.ndarray]]:
    """(mode, rule, threshold, accepted) of the four rules on one query set."""

    def p(model: ConfidenceModel, a: Answers) -> np.ndarray:
        return np.asarray(model.predict(feature_matrix(a.features, model.features)))

    zq = np.nan_to_num(single.score, nan=-np.inf)
    mq = np.nan_to_num(seq.score, nan=-np.inf)
    return [
        ("single", "model", fitted["threshold"], p(fitted["model"], single) >= fitted["threshold"]),
        ("single", "z", fitted["z"], zq >= fitted["z"]),
        (
            "sequence",
            "model",
            fitted["sequence_threshold"],
            p(fitted["sequence_model"], seq) >= fitted["sequence_threshold"],
        ),
        ("sequence", "mass", fitted["mass"], mq >= fitted["mass"]),
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nordland", type=int, default=200, help="Nordland winter frames used")
    ap.add_argument("--out", default=str(ROOT / "results" / "out_of_map.json"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    datasets = dataset_root()
    cache = FeatureCache(default_cache_dir())
    config = load_config("default")
    params = FilterParams()
    winter = list_images(datasets / "nordland_64x32" / "winter")
    nordland = [winter[i] for i in spread(len(winter), args.nordland)]
    rows: list[dict[str, Any]] = []
    maps: dict[str, Any] = {}
    for name in MAPS:
        ref, qry = GARDENS_POINT_PROTOCOLS[name]
        data = EvalData.frames(datasets / ref, datasets / qry, TOLERANCE)
        train_data, test_data = split_data(data, block=BLOCK)
        train = ScoreBank.build(config, train_data, cache=cache)
        fitted = fit_map(train, config, params)
        r_train, _ = block_parts(len(data.reference))
        _, q_test = block_parts(len(data.query))
        outside = out_of_map(data.gt, q_test, r_train)
        query_sets = {
            "nordland": (nordland, np.ones(len(nordland), dtype=bool)),
            "gp_night_removed": (test_data.query, outside),
        }
        maps[name] = {
            "n_reference": train.n_db,
            "thresholds": {
                k: float(fitted[k]) for k in ("threshold", "z", "sequence_threshold", "mass")
            },
            "train": fitted["train"],
            "models": {
                "single": fitted["model"].to_dict(),
                "sequence": fitted["sequence_model"].to_dict(),
            },
        }
        for qname, (queries, out_mask) in query_sets.items():
            gt = np.zeros((len(queries), train.n_db), dtype=bool)
            bank = ScoreBank.build(
                config, EvalData(train_data.reference, list(queries), gt, "none"), cache=cache
            )
            results = bank.results(config)
            routes = RouteMap.from_metadata(bank.n_db)
            single = single_answers(results, None, routes)
            seq = sequence_answers(results, None, routes, params)
            for mode, rule, thr, acc in decisions(fitted, single, seq):
                rows.append(
                    {
                        "map": name,
                        "queries": qname,
                        "mode": mode,
                        "rule": rule,
                        "threshold": float(thr),
                        "result": false_accepts(acc, out_mask),
                    }
                )
            print(f"{name} <- {qname}: {len(queries)} queries", flush=True)
    report = {
        "machine": machine_description(),
        "target_precision": TARGET,
        "goal": GOAL,
        "nordland_frames": len(nordland),
        "filter": vars(params) if hasattr(params, "__dict__") else str(params),
        "maps": maps,
        "rows": rows,
        "wall_s": time.perf_counter() - t0,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=str))
    print(table(rows))
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
