"""Places that are not in the map, out of the box: how often does the bundled preset accept
an answer for a frame from elsewhere, and what does refusing them cost on the map?

    python -m bench.out_of_map [--config default] [--maps gp_dl_dr,...] [--foreign 200]
        [--nordland-frames 800] [--out docs/experiments/acceptance/out_of_map.json]

The decisions are the service's: :class:`hmpf.acceptance.Policy` applied through
:func:`hmpf.evaluation.acceptance.decide` / :func:`~hmpf.evaluation.acceptance.apply_acceptance`
(rules ``p_correct``, ``quality``, ``lock``, the hysteresis and the filter's off-map state
as the service runs them). Three policies per map:

* ``shipped``: the preset as a new user gets it (``load_config(preset)``: its shipped
  models, ``hmpf/presets/acceptance/<preset>.json``; no ``hmpf-calibrate`` step). They were
  fitted on the training parts of these very routes (``bench/shipped_acceptance.py``), so
  the test parts below are new frames but not new places or cameras;
* ``held_out``: leave one route out, the models fitted by ``bench/shipped_acceptance.py``'s
  own procedure (:func:`shipped_acceptance.held_out`) on the *other* routes' training parts
  only: how the shipped procedure carries to a map it never saw;
* ``no_model``: the quality / lock rules (what a preset without a shipped model decides),
  for comparison;
* ``calibrated``: the route's own models, as ``hmpf-calibrate --config <preset> --fit-only
  --sequence`` fits them on the route's training part (the frames without ground truth
  beyond the route's own; :func:`hmpf.evaluation.calibrate.fit_config_acceptance`, its
  filter settings with them). Its single-frame model keeps the shipped model's off-map
  hinges (:func:`hmpf.evaluation.acceptance.carried_terms`) and its sequence model the
  shipped stay threshold and evidence floor; the entry's ``calibrated_fit.without_carried``
  and ``without_stay`` give the same fit without them, for comparison.

Each map is a route of ``bench/shipped_acceptance.py`` (Gardens Point's three protocols,
Nordland summer -> winter, the preset on all), split as ``hmpf-calibrate`` splits it
(alternating stretches of 20 frames). Two sets of frames the map does not cover:

* ``foreign``: ``--foreign`` frames of another data set spread evenly over it (Nordland
  winter thumbnails against a Gardens Point map, Gardens Point night_right against the
  Nordland map) against the route's *test* part; single frame, and driven in order as one
  vehicle in sequence mode (every frame counts);
* ``removed``: the route's test-part queries against its *training* part's references, i.e.
  the map with the queries' own references removed (the same route's neighbouring places:
  harder than another data set). Queries whose +-2-frame ground truth still reaches a
  training reference (the two frames either side of each join of the 20-frame stretches)
  are left out of the count: for them the place *is* in the map. Sequence mode drives every
  test query in order.

A false accept is an accepted answer for a frame off the map; the goal is <= 1 %
in both modes and a mean ``p_correct`` <= 0.1 off the map. Beside it, in the map (the test
part against its own references, :func:`shipped_acceptance.evaluate`): the share accepted
and the precision reached, lock flips per 100 frames, the sequence recall@1, ECE, and a
drive that leaves the map and comes back.

Writes the JSON report (every entry names the preset, its config digest and the models;
the report the machine, date and git commit) and prints Markdown tables.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.shipped_acceptance import (
    BLOCK,
    ROUTES,
    Route,
    add_route_arguments,
    evaluate,
    held_out_fit,
    model_sets,
    report_head,
    route_policies,
    spread,
)
from hmpf.acceptance import Policy
from hmpf.config import HierarchyConfig
from hmpf.evaluation.acceptance import (
    Answers,
    apply_acceptance,
    sequence_answers,
    single_answers,
)
from hmpf.evaluation.calibrate import fit_config_acceptance
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import ScoreBank
from hmpf.features import FeatureCache, default_cache_dir
from hmpf.sequence import FilterParams, RouteMap

__all__ = ["block_parts", "false_accepts", "off_map_rows", "out_of_map", "spread", "table"]

#: The acceptance goals off the map: accepted share and mean ``p_correct`` of off-map frames.
GOAL = 0.01
GOAL_MEAN_P = 0.1
#: The goal for the lock on the map.
GOAL_FLIPS = 2.0
POLICIES = ("shipped", "held_out", "no_model", "calibrated")


# -- pure helpers -------------------------------------------------------------------------------


def block_parts(n: int, block: int = BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the training and test parts of the blocks split (as ``split_data``)."""
    blk = (np.arange(n) // block) % 2
    return np.flatnonzero(blk == 0), np.flatnonzero(blk == 1)


def out_of_map(full_gt: np.ndarray, queries: np.ndarray, map_refs: np.ndarray) -> np.ndarray:
    """(len(queries),) True where no ground-truth reference of the query is in the map."""
    gt = np.asarray(full_gt, dtype=bool)
    return ~gt[np.ix_(np.asarray(queries), np.asarray(map_refs))].any(axis=1)


def upper_95(k: int, n: int) -> float:
    """One-sided 95 % upper bound on a rate seen as ``k`` of ``n`` (Clopper-Pearson)."""
    from scipy.stats import beta

    return float(beta.ppf(0.95, k + 1, n - k)) if n and k < n else 1.0


def false_accepts(accepted: np.ndarray, outside: np.ndarray) -> dict[str, Any]:
    """Accepted answers among the out-of-map frames: count, share, and the one-sided 95 %
    upper bound on the rate (what the count can rule out)."""
    a = np.asarray(accepted, dtype=bool)
    o = np.asarray(outside, dtype=bool)
    if a.shape != o.shape:
        raise ValueError("accepted and outside must have the same shape")
    n, k = int(o.sum()), int((a & o).sum())
    return {
        "n": n,
        "false_accepts": k,
        "rate": k / n if n else None,
        "upper_95": upper_95(k, n),
        "met": (k / n <= GOAL) if n else None,
    }


def mean_p(p: Sequence[float | None], keep: np.ndarray) -> float | None:
    """Mean ``p_correct`` of the kept answers (None without a model)."""
    v = [x for x, k in zip(p, keep, strict=True) if k and x is not None]
    return float(np.mean(v)) if v else None


def off_map_rows(rep: dict[str, Any], outside: np.ndarray) -> dict[str, Any]:
    """An :func:`~hmpf.evaluation.acceptance.apply_acceptance` report on frames of which
    ``outside`` are off the map: the rule, false accepts and mean ``p_correct`` there, and
    (sequence mode) the share the filter said was off the map."""
    o = np.asarray(outside, dtype=bool)
    out = {
        "rule": rep["rule"],
        **false_accepts(np.asarray(rep["accepted_answers"], bool), o),
        "mean_p": mean_p(rep["p_correct"], o),
        "said_off_map": float(np.mean(np.asarray(rep["off_map"], bool)[o])) if o.any() else None,
    }
    out["mean_p_met"] = None if out["mean_p"] is None else out["mean_p"] <= GOAL_MEAN_P
    return out


def _f(x: float | None, fmt: str = ".3f") -> str:
    return "n/a" if x is None else format(x, fmt)


def table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of the off-map rows."""
    lines = [
        "| map | models | frames (off map) | mode | rule | false accepts | rate (95 % upper "
        "bound) | mean p_correct | said off map | goal <= 1 % / p <= 0.1 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        met = "n/a" if r["met"] is None else ("yes" if r["met"] else "no")
        if r["mean_p_met"] is not None:
            met += " / " + ("yes" if r["mean_p_met"] else "no")
        lines.append(
            f"| {r['map']} | {r['models']} | {r['queries']} ({r['n']}) | {r['mode']} | "
            f"{r['rule']} | {r['false_accepts']} | {_f(r['rate'])} ({r['upper_95']:.3f}) | "
            f"{_f(r['mean_p'])} | {_f(r['said_off_map'], '.2f')} | {met} |"
        )
    return "\n".join(lines)


def in_map_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of the in-map (test part) rows."""
    lines = [
        "| route (test part) | models | mode | rule | accepted | precision | ECE | "
        "flips / 100 | recall@1 | leave-and-return: away accepted, back after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['map']} ({r['n']}) | {r['models']} | {r['mode']} | {r['rule']} | "
            f"{r['accepted']:.3f} | {_f(r['precision'])} | {_f(r.get('ece'))} | "
            f"{_f(r.get('flips_per_100'), '.1f')} | {_f(r.get('recall_at_1'))} | "
            f"{r.get('leave_and_return', '')} |"
        )
    return "\n".join(lines)


# -- the removed-references protocol ------------------------------------------------------------


def removed_answers(
    route: Route, config: HierarchyConfig, params: Sequence[FilterParams], cache: FeatureCache
) -> tuple[Answers, list[Answers], np.ndarray]:
    """The route's test queries answered against its training part's references (single
    frame; sequence mode, driven in order through the filter of each of ``params``), and
    which of them are off that map."""
    data = route.data
    r_train, _ = block_parts(len(data.reference))
    _, q_test = block_parts(len(data.query))
    assert [data.query[i] for i in q_test] == list(route.test_data.query)
    assert [data.reference[i] for i in r_train] == list(route.train_data.reference)
    gt = np.asarray(data.gt, bool)[np.ix_(q_test, r_train)]
    outside = out_of_map(data.gt, q_test, r_train)
    bank = ScoreBank.build(
        config,
        EvalData(route.train_data.reference, route.test_data.query, gt, data.ground_truth),
        cache=cache,
    )
    # The map is half the route's references: the route's prior stands in for its own.
    bank.map_prior = route.map_prior
    routes = RouteMap.from_metadata(bank.n_db)
    results = bank.results(config)
    profile = bank.profile(config)
    single = single_answers(results, gt, routes, profile)
    seqs = [sequence_answers(results, gt, routes, p, None, profile) for p in params]
    return single, seqs, outside


def calibrated(
    route: Route, preset: HierarchyConfig, cache: FeatureCache
) -> tuple[Policy, FilterParams, dict[str, Any]]:
    """The route's own acceptance, as ``hmpf-calibrate --config <preset> --fit-only
    --sequence`` fits it on the route's training part (no foreign frames: the calibrator
    has none): the policy, its filter settings and what the fit says (thresholds, the
    off-map terms carried from ``preset``'s shipped model, and, for comparison, the
    foreign frames' single-frame figures of the same fit without them, and the test part's
    sequence figures without the stay threshold it carries)."""
    bank = ScoreBank.build(route.config, route.train_data, cache=cache)
    bank.map_prior = route.map_prior
    fit = fit_config_acceptance(preset, bank, sequence=True)
    assert fit.sequence_params is not None and fit.confidence is not None
    params = fit.sequence_params
    policy = Policy.of(fit.config.acceptance, lock_mass=params.lock_mass)
    plain = fit_config_acceptance(
        preset.model_copy(update={"acceptance": None}), bank, sequence=False
    )
    bare = Policy.of(plain.config.acceptance, lock_mass=params.lock_mass)
    ev = evaluate(route, bare, params)
    unstayed = replace(policy, sequence_stay_threshold=None, sequence_stay_ref_z=None)
    q = evaluate(route, unstayed, params)["sequence"]
    return (
        policy,
        params,
        {
            "thresholds": policy.describe(),
            "carried": fit.confidence["single"].get("carried", {}),
            "filter": {k: getattr(params, k) for k in params.__dataclass_fields__},
            "without_carried": {
                "single_threshold": bare.model_threshold,
                "foreign_single_mean_p": ev["foreign"]["single_mean_p"],
                "foreign_single_accepted": ev["foreign"]["single_accepted"],
                "in_map_single": ev["single"],
            },
            "without_stay": {
                k: q[k] for k in ("accepted", "precision", "flips_per_100", "recall_at_1")
            },
        },
    )


# -- the run ------------------------------------------------------------------------------------


def label(preset: str, digest: str, models: str) -> dict[str, str]:
    """What a figure belongs to."""
    return {"preset": preset, "digest": digest, "models": models}


def rows_of(
    name: str, who: dict[str, str], ev: dict[str, Any], removed: dict[str, Any]
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One map and policy's rows (``who``: the policy's label, its models named short): off
    the map (foreign frames, then removed stretches) and in the map."""
    common = {"map": name, **who}
    f = ev["foreign"]
    rows = []
    for mode in ("single", "sequence"):
        n = f["n"]
        k = int(round(f[f"{mode}_accepted"] * n))
        mp = f[f"{mode}_mean_p"]
        rows.append(
            {
                **common,
                "queries": "foreign",
                "mode": mode,
                "rule": ev[mode]["rule"],
                "n": n,
                "false_accepts": k,
                "rate": k / n if n else None,
                "upper_95": upper_95(k, n),
                "met": (k / n <= GOAL) if n else None,
                "mean_p": mp,
                "mean_p_met": None if mp is None else mp <= GOAL_MEAN_P,
                "said_off_map": f["sequence_off_map"] if mode == "sequence" else None,
            }
        )
    for mode in ("single", "sequence"):
        rows.append({**common, "queries": "removed", "mode": mode, **removed[mode]})
    t = ev["leave_and_return"]
    in_map = []
    for mode in ("single", "sequence"):
        row = {**common, "mode": mode, **ev[mode]}
        if mode == "sequence":
            row["leave_and_return"] = (
                f"{t['away_accepted']:.3f}, {t['frames_to_accept_after_return']}"
            )
        in_map.append(row)
    return rows, in_map


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    ap.add_argument("--maps", default=",".join(ROUTES), help="maps to test (comma-separated)")
    add_json(ap, "--out", default=str(ROOT / "docs/experiments/acceptance/out_of_map.json"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    names = args.maps.split(",")
    # Every route's training part is needed for the held-out folds, whichever maps are shown.
    sets = model_sets(args.config, ROUTES, args.foreign, args.nordland_frames)
    config, params = sets.config, sets.params
    digest = config.digest()
    cache = FeatureCache(default_cache_dir())
    prov = provenance(args.config, config, args)
    goals = {"off_map_accepted": GOAL, "off_map_mean_p": GOAL_MEAN_P, "flips": GOAL_FLIPS}
    note = "2 shared CPU cores (other jobs running): the figures do not depend on it, wall_s does"
    report: dict[str, Any] = {
        **prov,
        **report_head(args, sets, note, goals),
        "maps": {},
        "rows": [],
        "in_map": [],
    }
    for i, route in enumerate(sets.routes):
        if route.name not in names:
            continue
        own, own_params, own_fit = calibrated(route, sets.shipped_config, cache)
        entry: dict[str, Any] = {
            "foreign": ROUTES[route.name][2],
            "n_test": route.n_test,
            "n_reference_test": route.test.n_db,
            "n_reference_train": route.train.n_db,
            "held_out_fit": held_out_fit(sets, i),
            "calibrated_fit": own_fit,
        }
        policies = {
            **{k: (pol, models, params) for k, (pol, models) in route_policies(sets, i).items()},
            "calibrated": (
                own,
                f"calibrated: hmpf-calibrate --config {args.config} --fit-only --sequence "
                "on the route's training part",
                own_params,
            ),
        }
        # The removed protocol's drives through the preset's filter and the calibrated one.
        r_single, (r_preset, r_own), outside = removed_answers(
            route, config, (params, own_params), cache
        )
        for key, (policy, models, p) in policies.items():
            r_seq = r_own if key == "calibrated" else r_preset
            who = label(args.config, digest, models)
            ev = evaluate(route, policy, p)
            ev["sequence"] = {
                k: v for k, v in ev["sequence"].items() if k not in ("p_correct", "correct")
            }
            removed = {
                "single": off_map_rows(apply_acceptance(policy, r_single), outside),
                "sequence": off_map_rows(apply_acceptance(policy, r_seq, sequence=True), outside),
            }
            entry[key] = {**who, **ev, "removed": removed}
            short = {**who, "models": key.replace("_", " ")}
            rows, in_map = rows_of(route.name, short, ev, removed)
            report["rows"] += rows
            report["in_map"] += in_map
        report["maps"][route.name] = entry
        print(f"{route.name} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["wall_s"] = time.perf_counter() - t0
    out = write_record(args.out, report, prov=prov)
    print(f"preset {args.config!r} (digest {digest[:12]}), {report['machine']}")
    print(table(report["rows"]))
    print()
    print(in_map_table(report["in_map"]))
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
