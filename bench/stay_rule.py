"""The stay threshold's evidence floor, chosen on drives that leave the map and come back.

    python -m bench.stay_rule [--config default] [--foreign 200] [--nordland-frames 800]
        [--out docs/experiments/acceptance/stay_rule.json]

The sequence model's stay threshold (hysteresis, :mod:`hmpf.acceptance`) keeps an estimate
accepted on the previous frame at a lower bar than a new one needs. When the vehicle leaves
the map, the filter carries its estimate forward for a frame or two before its off-map
state takes the mass, and the model, which reads mostly how sure the filter is, still gives
that first frame away 0.9-0.98: the stay threshold (0.9) accepts it, the entry threshold
(0.98) does not. The frame's own evidence says otherwise: its score at the estimate's
reference is below what unrelated references get (``sequence_ref_z`` well under 0). The
floor ``sequence_stay_ref_z`` lets the stay threshold apply only at or above it.

Chosen on the *training* parts of every route of ``bench/shipped_acceptance.py`` (the
parts its models are fitted on): each training drive (speeds 1, 2 and 3, every offset)
leaves the map three times (at a quarter, half and three quarters of it) for
:data:`BLOCK` frames of another data set (the route's foreign frames), then comes back.
For each floor of :data:`FLOORS` (and none), with the models fitted on all training parts
(the shipped fit) and with each held-out fold's, as the service decides
(:func:`hmpf.evaluation.acceptance.decide`): frames accepted while away (and of them the
first frame of a leave), the share of in-map frames accepted, their precision and lock
flips per 100. The choice: the least strict floor at which the shipped fit accepts no
more away frames than its entry threshold alone does (the stay then adds none). The test
parts are driven the same way (one speed-1 drive each, three leaves) and reported, not
used.

Writes the JSON record (preset, digest, machine, date, commit) and prints Markdown tables.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.shipped_acceptance import (
    ROUTES,
    Route,
    add_route_arguments,
    fit_recipe,
    flips,
    held_out,
    out_of_the_box,
    recipe_routes,
    shipped_recipe,
    training_part,
)
from hmpf.acceptance import Policy
from hmpf.evaluation.acceptance import decide, sequence_answers
from hmpf.evaluation.sequence import Drive, speed_drive, training_drives
from hmpf.features import FeatureCache
from hmpf.runtime import default_cache_dir
from hmpf.sequence import FilterParams, RouteMap

__all__ = ["FLOORS", "choose", "leave_drives", "spliced", "tally"]

#: Frames of another data set per leave.
BLOCK = 8
#: Where along a drive it leaves (share of its steps).
LEAVES = (0.25, 0.5, 0.75)
#: The floors tried (None: no floor, the stay threshold as before).
FLOORS: tuple[float | None, ...] = (None, -2.0, -1.5, -1.0, -0.75, -0.5, -0.25, 0.0, 0.5)


def spliced(
    inside: np.ndarray, away: np.ndarray, at: Sequence[int], start: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``inside`` with :data:`BLOCK` consecutive frames of ``away`` inserted before each step
    of ``at`` (blocks taken in turn from ``start``, wrapping); and per step whether it is
    away."""
    frames: list[int] = []
    flag: list[bool] = []
    k = start
    marks = set(int(a) for a in at)
    for i, q in enumerate(np.asarray(inside, dtype=np.int64)):
        if i in marks and len(away):
            block = [int(away[(k + j) % len(away)]) for j in range(min(BLOCK, len(away)))]
            k += len(block)
            frames += block
            flag += [True] * len(block)
        frames.append(int(q))
        flag.append(False)
    return np.array(frames, dtype=np.int64), np.array(flag, dtype=bool)


def leave_drives(drives: Sequence[Drive], away: np.ndarray) -> tuple[list[Drive], np.ndarray]:
    """Each drive leaving the map at :data:`LEAVES` of its steps, for :data:`BLOCK` frames of
    ``away`` each (consecutive blocks across drives); and per step of all drives whether it
    is away."""
    out: list[Drive] = []
    flags: list[np.ndarray] = []
    k = 0
    for d in drives:
        n = len(d.frames)
        frames, flag = spliced(d.frames, away, [int(n * x) for x in LEAVES], k)
        k += int(flag.sum())
        out.append(Drive.along(frames))
        flags.append(flag)
    return out, np.concatenate(flags) if flags else np.zeros(0, dtype=bool)


def tally(
    accepted: np.ndarray, away: np.ndarray, correct: np.ndarray, drive: np.ndarray
) -> dict[str, Any]:
    """A policy's decisions on leave-and-return drives: away frames accepted (all, and the
    first of each leave), in-map frames accepted, their precision, lock flips (per drive,
    in-map frames only) per 100 in-map frames."""
    accepted, away = np.asarray(accepted, bool), np.asarray(away, bool)
    correct, drive = np.asarray(correct, bool), np.asarray(drive)
    before = np.r_[False, away[:-1]]
    before[np.r_[True, drive[1:] != drive[:-1]]] = False  # a drive's first step follows none
    first = away & ~before
    inside = ~away
    kept = accepted & inside
    return _shares(
        {
            "away": int(away.sum()),
            "away_accepted": int((accepted & away).sum()),
            "first_away_accepted": int((accepted & first).sum()),
            "leaves": int(first.sum()),
            "in_map": int(inside.sum()),
            "in_map_kept": int(kept.sum()),
            "in_map_right": int((kept & correct).sum()),
            "flips": sum(flips(accepted[inside & (drive == d)]) for d in np.unique(drive)),
        }
    )


#: The counts :func:`tally` keeps (summed by :func:`pooled`); the shares derive from them.
_COUNTS = (
    "away",
    "away_accepted",
    "first_away_accepted",
    "leaves",
    "in_map",
    "in_map_kept",
    "in_map_right",
    "flips",
)


def _shares(counts: dict[str, int]) -> dict[str, Any]:
    """``counts`` with the in-map share accepted, its precision and flips per 100 in-map
    frames."""
    n, kept = max(counts["in_map"], 1), counts["in_map_kept"]
    return {
        **counts,
        "in_map_accepted": kept / n,
        "precision": counts["in_map_right"] / kept if kept else None,
        "flips_per_100": 100.0 * counts["flips"] / n,
    }


def choose(rows: Sequence[dict[str, Any]], entry_away: int) -> float | None:
    """The least strict floor (rows in :data:`FLOORS` order, each with ``floor`` and the
    pooled ``away_accepted``) whose away frames accepted are no more than the entry
    threshold's alone (``entry_away``); None when no floor gets there."""
    for row in rows:
        if row["floor"] is not None and row["away_accepted"] <= entry_away:
            return float(row["floor"])
    return None


class Leaves:
    """One route part's leave-and-return drives through the filter."""

    def __init__(self, route: Route, params: FilterParams, which: str) -> None:
        bank = route.train if which == "train" else route.test
        nq = route.n_train if which == "train" else route.n_test
        routes = RouteMap.from_metadata(bank.n_db)
        results = bank.results(route.config)
        profile = bank.profile(route.config)
        drives = training_drives(nq) if which == "train" else [speed_drive(nq, 1.0)]
        driven, self.away = leave_drives(drives, np.arange(nq, bank.n_query))
        self.answers = sequence_answers(results, bank.gt, routes, params, driven, profile)

    def decide(self, policy: Policy) -> dict[str, Any]:
        acc = np.array([d.accepted for d in decide(policy, self.answers, sequence=True)], bool)
        assert self.answers.drive is not None
        return tally(acc, self.away, self.answers.correct, self.answers.drive)


def pooled(figs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Routes' :func:`tally` figures pooled: their counts summed, the shares of the sums."""
    return _shares({k: sum(f[k] for f in figs) for k in _COUNTS})


def grid(parts: dict[str, Leaves], policies: dict[str, Policy]) -> list[dict[str, Any]]:
    """Per floor of :data:`FLOORS`: each route's figures with its policy, and pooled; first
    the entry threshold alone (``floor`` ``"entry only"``)."""
    rows = []
    for floor in ("entry only", *FLOORS):
        per = {}
        for name, leaves in parts.items():
            p = policies[name]
            rule = (
                replace(p, sequence_stay_threshold=None)
                if floor == "entry only"
                else replace(p, sequence_stay_ref_z=floor)
            )
            per[name] = leaves.decide(rule)
        rows.append({"floor": floor, "routes": per, **pooled(list(per.values()))})
    return rows


def _f(x: float | None, fmt: str) -> str:
    return "n/a" if x is None else format(x, fmt)


def table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: a row per floor, pooled."""
    head = (
        "| floor | away accepted (first of a leave) | in-map accepted | precision | "
        "flips / 100 |\n|---|---|---|---|---|"
    )
    lines = [head]
    for r in rows:
        floor = r["floor"] if isinstance(r["floor"], str) else _f(r["floor"], "g")
        lines.append(
            f"| {'none' if r['floor'] is None else floor} | {r['away_accepted']} of {r['away']} "
            f"({r['first_away_accepted']} of {r['leaves']}) | {r['in_map_accepted']:.3f} | "
            f"{_f(r['precision'], '.4f')} | {r['flips_per_100']:.1f} |"
        )
    return "\n".join(lines)


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    add_json(ap, "--out", help="JSON record (default docs/experiments/acceptance/stay_rule.json)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    config, _, _ = out_of_the_box(args.config)
    prov = provenance(args.config, config, args)
    params = config.sequence_params()
    cache = FeatureCache(default_cache_dir())
    recipe = shipped_recipe(args.config)._replace(stay_ref_z=None)
    names = list(ROUTES)
    routes, priors = recipe_routes(config, names, cache, args.foreign, args.nordland_frames, recipe)
    train = [training_part(r, params) for r in routes]
    shipped, _ = fit_recipe(train, recipe)
    folds = {r.name: p for r, (p, _) in zip(routes, held_out(train, recipe), strict=True)}
    print(f"models fitted ({time.perf_counter() - t0:.0f} s)", flush=True)
    report: dict[str, Any] = {
        "config": args.config,
        "recipe": recipe.describe(),
        "map_priors": priors,
        "block": BLOCK,
        "leaves": list(LEAVES),
    }
    for which in ("train", "test"):
        parts = {r.name: Leaves(r, params, which) for r in routes}
        report[which] = {
            "shipped_fit": grid(parts, dict.fromkeys(parts, shipped)),
            "held_out": grid(parts, folds),
        }
    rows = report["train"]["shipped_fit"]
    report["chosen"] = choose(rows[1:], rows[0]["away_accepted"])
    report["wall_s"] = time.perf_counter() - t0
    for which in ("train", "test"):
        for fit in ("shipped_fit", "held_out"):
            print(f"\n{which}, {fit}:\n{table(report[which][fit])}")
    print(f"\nchosen floor (training parts, shipped fit): {report['chosen']}")
    out = write_record(
        args.out or ROOT / "docs" / "experiments" / "acceptance" / "stay_rule.json",
        report,
        prov=prov,
    )
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
