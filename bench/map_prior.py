"""A map-level prior for the acceptance models: the hierarchy's pseudo-query recall on the map.

    python -m bench.map_prior [--config default] [--foreign 200] [--nordland-frames 800]
        [--out docs/experiments/acceptance/map_prior.json]

Why (``docs/experiments/acceptance/README.md``): the shipped models pool Gardens
Point, where the preset's evidence tells right answers from wrong ones, with Nordland, where
it does not (AUC 0.51-0.54), and nothing in an answer's features says which kind of map it
comes from. So the pooled model is too cautious on Gardens Point's night protocols and, left
out of the fit, accepts Nordland's wrong answers.

What is measured: a feature of the *map*, available without a query or ground truth, that
says how well the preset tells this map's places apart: ``map_prior``, the log-odds of the
preset's recall@1 on pseudo-queries made from the map's own references
(:mod:`hmpf.evaluation.pseudo`: changed copies of references answered against the map with
their source masked; right within +-2 along the route), computed on the route's whole
reference traverse (Nordland: its first ``--nordland-frames`` frames, as the routes use). It
enters the models as a fixed offset (:data:`hmpf.evaluation.acceptance.OFFSET_FEATURES`:
coefficient 1, not fitted), so a held-out route's prior comes from its own map even where
the training maps' priors are all alike (a fitted coefficient could not be learnt from
three Gardens Point maps and carried to Nordland).

Five variants, each fitted as the shipped models are (:mod:`bench.shipped_acceptance`:
pooled over the routes' training parts, thresholds for 99 % precision on out-of-fold
predictions) and checked with the models fitted on all routes (``pooled``) and leave one
route out (``held_out``) on every route's test part and on its whole traverse
(:func:`bench.shipped_acceptance.evaluate_whole`: no stretches joined, so no estimate is
wrong only because the part joins two stretches):

* ``without``: the shipped procedure as it is;
* ``map_prior``: ``map_prior`` added to both models as an offset;
* ``map_prior_stay``: the same, and the sequence stay threshold (hysteresis) chosen as the
  service decides: the lowest of 0.5 / 0.6 / 0.7 / 0.8 / 0.9 at which every training route's
  out-of-fold drives keep 99 % precision with the stay (else the entry threshold itself);
* ``map_prior_every_route``: the same, with the sequence entry threshold chosen so that
  every training route's out-of-fold answers (not the routes pooled) keep 99 % precision
  frame by frame (:func:`every_route_threshold`);
* ``map_prior_stay_high``: the offset, and the stay threshold fixed at :data:`HIGH_STAY`
  (an accepted estimate stays accepted while its ``p_correct`` is at least 0.9, not 0.5).

Nothing is shipped by this bench.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from bench import shipped_acceptance as sa
from bench.harness import ROOT, add_json, parser, provenance, write_record
from hmpf.acceptance import STAY_P, Policy
from hmpf.evaluation.acceptance import RoutePart
from hmpf.features import FeatureCache
from hmpf.runtime import default_cache_dir

OUT = ROOT / "docs" / "experiments" / "acceptance" / "map_prior.json"
#: Stay thresholds tried by ``map_prior_stay``, lowest first (the entry threshold caps them).
STAYS = (STAY_P, 0.6, 0.7, 0.8, 0.9)
Features = tuple[tuple[str, ...], tuple[str, ...]]
#: The fixed stay threshold of ``map_prior_stay_high``.
HIGH_STAY = 0.9
#: The experience log's default threshold (``experience_min_p_correct``): the share of
#: sequence answers at or above it is what a recording service would keep.
RECORD_P = 0.99


def choose_stay(seqs: list[RoutePart], policy: Policy) -> tuple[Policy, dict[str, Any]]:
    """The lowest stay threshold of :data:`STAYS` (at most the entry threshold) at which
    every route's out-of-fold training drives, decided with the stay, keep the target
    precision; the entry threshold when none does."""
    entry = policy.sequence_threshold
    assert entry is not None
    tried = {}
    for stay in [s for s in STAYS if s < entry] + [entry]:
        candidate = replace(policy, sequence_stay_threshold=stay)
        rows = sa.as_decided(seqs, candidate)
        tried[f"{stay:.3f}"] = rows
        worst = min(
            (r["with_stay"]["precision"] for r in rows.values() if r["with_stay"]["precision"]),
            default=1.0,
        )
        if worst >= sa.TARGET:
            return candidate, {"stay_threshold": stay, "tried": tried}
    return replace(policy, sequence_stay_threshold=entry), {"stay_threshold": entry, "tried": tried}


def every_route_threshold(seqs: list[RoutePart], policy: Policy) -> float:
    """The lowest sequence threshold at which the out-of-fold training answers of *every*
    route, frame by frame, are accepted at the target precision or not at all (the
    shipped threshold asks it of the routes pooled)."""
    assert policy.sequence_model is not None
    pred, y, g, inside = sa.route_out_of_fold(
        seqs, policy.sequence_model.features, outside_share=sa.OFF_SHARE, by="folds"
    )
    p, y, g = pred[inside], y[inside].astype(bool), g[inside]
    for t in np.unique(p):
        acc = p >= t
        if all(y[acc & (g == k)].mean() >= sa.TARGET for k in np.unique(g[acc])):
            return float(t)
    return 1.0


def fit_variant(
    parts: list[tuple[RoutePart, RoutePart]],
    features: Features,
    stay: bool | float,
    every: bool = False,
) -> tuple[Policy, dict[str, Any]]:
    """The pooled fit of ``parts`` on ``features``; ``stay``: True, the stay threshold
    chosen as decided (:func:`choose_stay`); a number, that stay threshold (at most the
    entry threshold); False, the shipped one. ``every``: the entry threshold of
    :func:`every_route_threshold`."""
    policy, train = sa.fit([p[0] for p in parts], [p[1] for p in parts], features)
    if every:
        entry = every_route_threshold([p[1] for p in parts], policy)
        policy = replace(
            policy,
            sequence_threshold=entry,
            sequence_stay_threshold=min(STAY_P, entry),
        )
        train["every_route_threshold"] = entry
    if stay is True:
        policy, train["stay_choice"] = choose_stay([p[1] for p in parts], policy)
        train["stay_threshold"] = policy.sequence_stay_threshold
    elif stay is not False:
        cap = policy.sequence_threshold
        assert cap is not None
        policy = replace(policy, sequence_stay_threshold=min(float(stay), cap))
        train["stay_threshold"] = policy.sequence_stay_threshold
    return policy, train


def figures(ev: dict[str, Any]) -> dict[str, Any]:
    """What the report keeps of :func:`bench.shipped_acceptance.evaluate`."""
    keep = ("accepted", "precision", "ece", "right", "recall_at_1", "flips_per_100")
    seq = {k: ev["sequence"][k] for k in keep}
    seq["entry_only"] = ev["sequence"]["entry_only"]
    # what a recording service keeps at its default threshold (p_correct >= 0.99)
    p = np.array([np.nan if x is None else x for x in ev["sequence"]["p_correct"]], float)
    right = np.array(ev["sequence"]["correct"], bool)
    sure = p >= RECORD_P
    seq["recordable"] = {
        "p_at_least": RECORD_P,
        "share": float(sure.mean()),
        "precision": float(right[sure].mean()) if sure.any() else None,
    }
    return {
        "single": ev["single"],
        "sequence": seq,
        "foreign": ev["foreign"],
        "leave_and_return": ev["leave_and_return"],
    }


def main() -> int:
    ap = parser(__doc__)
    sa.add_route_arguments(ap)
    add_json(ap, "--out", help=f"JSON report (default {OUT.relative_to(ROOT)})")
    args = ap.parse_args()
    t0 = time.perf_counter()
    config = sa.out_of_the_box(args.config)[1]
    prov = provenance(args.config, config, args)
    params = config.sequence_params()
    cache = FeatureCache(default_cache_dir())
    names = list(sa.ROUTES)
    priors = sa.route_priors(config, names, cache, args.nordland_frames)
    routes = [
        sa.Route(
            n, config, cache, args.foreign, sa.limit_of(n, args.nordland_frames),
            priors[n]["map_prior"],
        )
        for n in names
    ]  # fmt: skip
    print(f"banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    parts = [sa.training_part(r, params) for r in routes]
    plain: Features = (sa.SINGLE_FEATURES, sa.SEQUENCE_FEATURES)
    with_prior: Features = (plain[0] + ("map_prior",), plain[1] + ("map_prior",))
    variants = {
        "without": (plain, False, False),
        "map_prior": (with_prior, False, False),
        "map_prior_stay": (with_prior, True, False),
        "map_prior_every_route": (with_prior, True, True),
        "map_prior_stay_high": (with_prior, HIGH_STAY, False),
    }
    report: dict[str, Any] = {
        "config": args.config,
        "target_precision": sa.TARGET,
        "nordland_frames": args.nordland_frames or "all",
        "foreign_frames": args.foreign,
        "pseudo_recall": {sa.ROUTES[n][0]: priors[n] for n in names},
        "variants": {},
    }
    for vname, (features, stay, every) in variants.items():
        pooled, train = fit_variant(parts, features, stay, every)
        folds = []
        for i in range(len(parts)):
            rest = [p for j, p in enumerate(parts) if j != i]
            folds.append(fit_variant(rest, features, stay, every))
        runs: dict[str, list[dict[str, Any]]] = {"pooled": [], "held_out": []}
        per_route: dict[str, Any] = {}
        for i, r in enumerate(routes):
            row = {}
            for label, policy in (("pooled", pooled), ("held_out", folds[i][0])):
                ev = sa.evaluate(r, policy, params)
                runs[label].append(ev)
                row[label] = figures(ev)
                row[label]["thresholds"] = policy.describe()
                row[label]["whole"] = sa.evaluate_whole(r, policy, params)
                print(
                    f"{vname:15s} {r.name:13s} {label:8s} single {ev['single']['accepted']:.3f}"
                    f" ({ev['single']['precision']}) sequence {ev['sequence']['accepted']:.3f}"
                    f" ({ev['sequence']['precision']}) ECE {ev['sequence']['ece']:.3f}; foreign"
                    f" {ev['foreign']['single_accepted']:.3f} / "
                    f"{ev['foreign']['sequence_accepted']:.3f}",
                    flush=True,
                )
            per_route[r.name] = row
        report["variants"][vname] = {
            "single_features": list(features[0]),
            "sequence_features": list(features[1]),
            "stay_chosen": stay,
            "every_route_threshold": every,
            "pooled_fit": {"thresholds": pooled.describe(), "train": train},
            "routes": per_route,
            "pooled_sequence_ece": {k: sa.pooled_ece(v) for k, v in runs.items()},
        }
        print(f"{vname}: pooled sequence ECE {report['variants'][vname]['pooled_sequence_ece']}")
    report["wall_s"] = time.perf_counter() - t0
    out = write_record(args.out or OUT, report, prov=prov)
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
