"""The single-frame model's off-map hinges, chosen on the training parts.

    python -m bench.offmap_hinge [--config default] [--foreign 200] [--nordland-frames 800]
        [--out docs/experiments/acceptance/offmap_hinge.json]

A frame from a place the map does not hold gets every answer wrong, yet the single-frame
model gave such frames a ``p_correct`` of about a third on the Gardens Point maps (none
accepted: the threshold keeps them out, but the number is not a probability there). Their
evidence says where they come from: their tier-1 scores lie below what unrelated places
score at the answer (``ref_z`` < 0) and at every other candidate (``cand_z`` < 0), which
almost no in-map answer does. The hinges ``ref_z_low`` (``min(ref_z, 0)``) and
``cand_z_low`` (``min(cand_z - knot, 0)``: the best of a dozen or more candidates lies above
0 even for a frame that scores like unrelated places, so its knot is tried at 0, 0.5 and 1)
carry that, fitted in a second stage on top of the shipped model
(:data:`hmpf.evaluation.acceptance.STAGED_FEATURES`,
:meth:`~hmpf.confidence.ConfidenceModel.fit_staged`), so answers whose hinges are 0 keep
their probability.

Each variant of :data:`VARIANTS` (the shipped recipe's single-frame features plus those
hinges) on the *training* parts of every route of ``bench/shipped_acceptance.py``, leave
one route out (each route's training answers predicted by the model fitted on the other
routes' training parts): the in-map answers' ECE, and the mean ``p_correct`` of the
route's foreign training frames (another data set against its map) and of its removed
stretches (its own queries with their references taken out). The choice: the variant
whose highest foreign mean ``p_correct`` over the routes is lowest (the shipped knot,
:data:`hmpf.confidence.CAND_Z_KNOT`, is recorded beside it). The *test* parts are
reported for every variant (shipped fit and held-out folds: accepted share, precision,
ECE, another route's frames' mean ``p_correct``), not used.

Writes the JSON record (preset, digest, machine, date, commit) and prints Markdown tables.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.shipped_acceptance import (
    ROUTES,
    Recipe,
    Route,
    _figures,
    _mean_p,
    add_route_arguments,
    fit_recipe,
    held_out,
    out_of_the_box,
    recipe_routes,
    shipped_recipe,
    training_part,
)
from hmpf.acceptance import Policy
from hmpf.confidence import CAND_Z_KNOT, expected_calibration_error
from hmpf.evaluation.acceptance import (
    Answers,
    RoutePart,
    apply_acceptance,
    route_out_of_fold,
    single_answers,
)
from hmpf.features import FeatureCache
from hmpf.runtime import default_cache_dir
from hmpf.sequence import RouteMap

__all__ = [
    "HINGES",
    "VARIANTS",
    "below_unrelated",
    "choose",
    "hinged",
    "set_knot",
    "training_figures",
]

#: The hinges a variant may add.
HINGES = ("ref_z_low", "cand_z_low")
#: Variant name -> (hinges added to the single-frame model, fitted in a second stage;
#: ``cand_z_low``'s knot: ``min(cand_z - knot, 0)``, None where it is not used).
VARIANTS: dict[str, tuple[tuple[str, ...], float | None]] = {
    "none": ((), None),
    "ref_z_low": (("ref_z_low",), None),
    **{f"ref_z_low+cand_z_low@{k:g}": (HINGES, k) for k in (0.0, 0.5, 1.0)},
}


def set_knot(answers: Answers | None, knot: float | None) -> None:
    """Give every answer's ``cand_z_low`` the knot ``knot`` (from its ``cand_z``), in
    place; None: leave them."""
    if answers is None or knot is None:
        return
    for f in answers.features:
        f["cand_z_low"] = min(f["cand_z"] - knot, 0.0)


def with_hinges(recipe: Recipe, hinges: tuple[str, ...]) -> Recipe:
    """``recipe`` with its single-frame model's hinges replaced by ``hinges`` (placed
    before ``map_prior``, as ``--single-extra`` places them)."""
    plain = tuple(f for f in recipe.single if f not in HINGES)
    head = tuple(f for f in plain if f != "map_prior")
    tail = ("map_prior",) if "map_prior" in plain else ()
    return recipe._replace(single=head + hinges + tail)


def hinged(features: list[dict[str, float]], names: tuple[str, ...]) -> float:
    """The share of answers with one of the hinges among ``names`` below 0 (answers whose
    probability the second stage moves)."""
    hinges = [n for n in names if n in HINGES]
    if not features or not hinges:
        return 0.0
    return float(np.mean([any(f[n] < 0 for n in hinges) for f in features]))


def below_unrelated(features: list[dict[str, float]]) -> float:
    """The share of answers whose ``ref_z`` is below 0 (the answer scores below what
    unrelated places get there)."""
    return float(np.mean([f["ref_z"] < 0 for f in features])) if features else 0.0


def training_figures(
    parts: list[RoutePart], n_train: list[int], names: tuple[str, ...], share: float
) -> dict[str, dict[str, float]]:
    """Per route of ``parts`` (single-frame training parts, :func:`training_part`), leave
    one route out: the in-map answers' ECE and share right, the mean ``p_correct`` of its
    foreign frames (outside answers whose query index is at or past ``n_train``, the
    route's in-map query count) and of its removed stretches (the other outside answers);
    the shares of in-map answers and foreign frames the hinges move (:func:`hinged`) and
    whose answer scores below unrelated places (:func:`below_unrelated`)."""
    p, y, g, inside = route_out_of_fold(parts, names, outside_share=share, by="routes")
    out: dict[str, dict[str, float]] = {}
    for k, (part, nq) in enumerate(zip(parts, n_train, strict=True)):
        assert part.outside is not None
        rows = g == k
        p_in, right = p[rows & inside], y[rows & inside].astype(bool)
        p_out = p[rows & ~inside]
        foreign = part.outside.query >= nq
        away = [f for f, a in zip(part.outside.features, foreign, strict=True) if a]
        out[part.name] = {
            "ece_in_map": expected_calibration_error(p_in, right),
            "right_in_map": float(right.mean()),
            "foreign_mean_p": float(p_out[foreign].mean()),
            "foreign_n": int(foreign.sum()),
            "removed_mean_p": float(p_out[~foreign].mean()),
            "removed_n": int((~foreign).sum()),
            "in_map_hinged": hinged(part.answers.features, names),
            "in_map_below_unrelated": below_unrelated(part.answers.features),
            "foreign_hinged": hinged(away, names),
            "foreign_below_unrelated": below_unrelated(away),
        }
    return out


def test_figures(
    route: Route, policy: Policy, knot: float | None = None, names: tuple[str, ...] = ()
) -> dict[str, Any]:
    """The single-frame policy on the route's test part and its foreign frames (with
    ``cand_z_low``'s knot ``knot``, :func:`set_knot`); with the model's features
    ``names``, the shares the hinges move."""
    bank, config = route.test, route.config
    routes = RouteMap.from_metadata(bank.n_db)
    results = bank.results(config)
    profile = bank.profile(config)
    nq, nf = route.n_test, route.n_foreign
    single = single_answers(results[:nq], bank.gt[:nq], routes, profile)
    foreign = single_answers(results[nq : nq + nf], None, routes, profile)
    set_knot(single, knot)
    set_knot(foreign, knot)
    fs = apply_acceptance(policy, foreign)
    return {
        **_figures(apply_acceptance(policy, single), single),
        "foreign_accepted": fs["accepted"],
        "foreign_mean_p": _mean_p(fs),
        "in_map_hinged": hinged(single.features, names),
        "in_map_below_unrelated": below_unrelated(single.features),
        "foreign_hinged": hinged(foreign.features, names),
        "foreign_below_unrelated": below_unrelated(foreign.features),
    }


def choose(train: dict[str, dict[str, dict[str, float]]]) -> str:
    """The variant whose highest foreign mean ``p_correct`` over the routes is lowest."""
    return min(train, key=lambda v: max(r["foreign_mean_p"] for r in train[v].values()))


def table(report: dict[str, Any]) -> str:
    lines = [
        "| variant | route | training, held out: ECE in map | foreign mean p | removed "
        "mean p | test, shipped fit: accepted (precision) | foreign mean p | test, "
        "held out: accepted (precision) | foreign mean p |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for v, rows in report["train"].items():
        for name, t in rows.items():
            s, h = report["test"][v]["shipped_fit"][name], report["test"][v]["held_out"][name]
            cells = [
                f"{t['ece_in_map']:.3f}",
                f"{t['foreign_mean_p']:.3f}",
                f"{t['removed_mean_p']:.3f}",
            ]
            for f in (s, h):
                prec = "" if f["precision"] is None else f" ({f['precision']:.3f})"
                cells += [f"{100 * f['accepted']:.0f} %{prec}", f"{f['foreign_mean_p']:.3f}"]
            lines.append(f"| {v} | {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    add_json(
        ap, "--out", help="JSON record (default docs/experiments/acceptance/offmap_hinge.json)"
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    config, _, _ = out_of_the_box(args.config)
    prov = provenance(args.config, config, args)
    params = config.sequence_params()
    cache = FeatureCache(default_cache_dir())
    base = with_hinges(shipped_recipe(args.config), ())
    names = list(ROUTES)
    routes, priors = recipe_routes(config, names, cache, args.foreign, args.nordland_frames, base)
    parts = [training_part(r, params) for r in routes]
    singles = [p[0] for p in parts]
    n_train = [r.n_train for r in routes]
    print(f"banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    report: dict[str, Any] = {
        "config": args.config,
        "recipe": base.describe(),
        "map_priors": priors,
        "variants": {k: {"hinges": list(h), "knot": kn} for k, (h, kn) in VARIANTS.items()},
        "shipped_knot": CAND_Z_KNOT,
        "train": {},
        "test": {},
    }
    for v, (hinges, knot) in VARIANTS.items():
        for part in singles:
            set_knot(part.answers, knot)
            set_knot(part.outside, knot)
        recipe = with_hinges(base, hinges)
        report["train"][v] = training_figures(singles, n_train, recipe.single, recipe.single_share)
        shipped, _ = fit_recipe(parts, recipe)
        folds = held_out(parts, recipe)
        report["test"][v] = {
            "single_threshold": shipped.model_threshold,
            "shipped_fit": {r.name: test_figures(r, shipped, knot, recipe.single) for r in routes},
            "held_out": {
                r.name: test_figures(r, f, knot, recipe.single)
                for r, (f, _) in zip(routes, folds, strict=True)
            },
        }
        print(f"{v} ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["chosen"] = choose(report["train"])
    report["wall_s"] = time.perf_counter() - t0
    print(table(report))
    print(f"\nchosen (training parts, held out): {report['chosen']}")
    out = write_record(
        args.out or ROOT / "docs" / "experiments" / "acceptance" / "offmap_hinge.json",
        report,
        prov=prov,
    )
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
