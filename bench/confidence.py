"""Calibrated confidence out of the box: is the bundled preset's ``p_correct`` a probability,
and what does its acceptance give on the map?

    python -m bench.confidence [--config default] [--foreign 200] [--nordland-frames 800]
        [--out docs/experiments/acceptance/confidence.json] [--plot PNG]

``p_correct`` and ``accepted`` are the service's: :class:`hmpf.acceptance.Policy` applied
through :func:`hmpf.evaluation.acceptance.apply_acceptance` (in sequence mode the model's
probability times the filter's on-the-map probability, with the hysteresis). Two model sets:

* ``shipped``: the preset as a new user gets it (``load_config(preset)``, its shipped
  models; no ``hmpf-calibrate`` step). Fitted on the training parts of these routes by
  ``bench/shipped_acceptance.py``: the test parts are new frames, not new places;
* ``held_out``: leave one route out, the same procedure
  (:func:`shipped_acceptance.held_out`) fitted on the other routes' training parts only,
  measured on the held-out route;

beside them the quality / lock rules (``no_model``: what a preset without a model decides).

The routes are ``bench/shipped_acceptance.py``'s (Gardens Point's three protocols, Nordland
summer -> winter; the preset on all), split as ``hmpf-calibrate`` splits them (alternating
stretches of 20 frames). On each route's *test* part, single frame and the test part driven
once, in order, in sequence mode:

* calibration: expected calibration error (10 bins), beside it the ECE a perfectly
  calibrated model would show on that many answers (:func:`ece_floor`), the reliability
  bins, the mean ``p_correct`` and the share right; pooled over the routes (every route,
  and the Gardens Point ones) for the goal (sequence ECE <= 0.05);
* acceptance: the share accepted by the policy and the precision reached (goal at
  precision >= 99 %: sequence >= 85 % on every Gardens Point protocol, >= 50 % on Nordland;
  single frame >= 30 % on each Gardens Point protocol), lock flips per 100 frames;
* off the map: the mean ``p_correct`` of ``--foreign`` frames of another data set
  (single frame; sequence mode driven in order): goal <= 0.1;
* which of the model's features carry information on the test part (ROC AUC of each alone,
  right vs wrong in-map answers; > 0.5: higher means right).

Writes the JSON report (every entry names the preset, its config digest and the models;
the report the machine, date and git commit), a reliability diagram, and prints Markdown
tables.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import rankdata

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.sequence import pyplot
from bench.shipped_acceptance import (
    ROUTES,
    TARGET,
    Route,
    add_route_arguments,
    flips,
    held_out_fit,
    model_sets,
    report_head,
    route_policies,
)
from hmpf.acceptance import Policy
from hmpf.confidence import (
    expected_calibration_error,
    feature_matrix,
    reliability,
)
from hmpf.config import HierarchyConfig
from hmpf.evaluation.acceptance import (
    Answers,
    apply_acceptance,
    sequence_answers,
    single_answers,
)
from hmpf.evaluation.sequence import Drive
from hmpf.sequence import FilterParams, RouteMap

#: The acceptance goals (bundled default preset, test parts / held-out folds).
GOAL_ECE = 0.05
GOAL_SEQUENCE = {"gp": 0.85, "nordland": 0.50}
GOAL_SINGLE_GP = 0.30
GOAL_MEAN_P = 0.1
GOAL_FLIPS = 2.0
MODES = ("single", "sequence")


# -- measures -----------------------------------------------------------------------------------


def auc(x: np.ndarray, y: np.ndarray) -> float:
    """ROC AUC of score ``x`` for right (``y``) vs wrong answers (Mann-Whitney, ties 1/2)."""
    y = np.asarray(y, dtype=bool)
    pos, neg = int(y.sum()), int((~y).sum())
    if not pos or not neg:
        return float("nan")
    ranks = rankdata(x)
    return float((ranks[y].sum() - pos * (pos + 1) / 2) / (pos * neg))


def ece_floor(p: np.ndarray, draws: int = 200, seed: int = 0) -> float:
    """Mean ECE of a *perfectly calibrated* model with the same predictions (outcomes drawn
    as Bernoulli(p)): what sampling alone costs on this many answers."""
    p = np.asarray(p, dtype=np.float64)
    if not len(p):
        return float("nan")
    rng = np.random.default_rng(seed)
    return float(
        np.mean([expected_calibration_error(p, rng.random(len(p)) < p) for _ in range(draws)])
    )


def calibration(p: Sequence[float | None], correct: np.ndarray) -> dict[str, Any]:
    """ECE, its sampling floor, the reliability bins, mean ``p`` and the share right of the
    answers with a ``p_correct`` (None: the rule has no model)."""
    keep = np.array([x is not None for x in p], dtype=bool)
    if not keep.any():
        return {"n": 0, "ece": None}
    pa = np.array([x for x in p if x is not None], dtype=np.float64)
    c = np.asarray(correct, dtype=bool)[keep]
    rel = reliability(pa, c)
    return {
        "n": int(len(pa)),
        "ece": expected_calibration_error(pa, c),
        "sampling_floor": ece_floor(pa),
        "mean_p": float(pa.mean()),
        "right": float(c.mean()),
        "reliability": {
            k: [None if not np.isfinite(x) else float(x) for x in np.asarray(v, np.float64)]
            for k, v in vars(rel).items()
        },
    }


def feature_auc(answers: Answers, names: Sequence[str]) -> dict[str, float]:
    """ROC AUC of each of ``names`` alone on ``answers``."""
    X = feature_matrix(answers.features, names)
    return {n: auc(X[:, j], answers.correct) for j, n in enumerate(names)}


def meets(mode: str, gp: bool, accepted: float, precision: float | None) -> bool | None:
    """Whether an accepted share at a precision meets the on-map acceptance goal (None: no goal
    for single frame on Nordland)."""
    if mode == "single":
        goal = GOAL_SINGLE_GP if gp else None
    else:
        goal = GOAL_SEQUENCE["gp" if gp else "nordland"]
    if goal is None:
        return None
    return precision is not None and precision >= TARGET and accepted >= goal


# -- one route ----------------------------------------------------------------------------------


def route_answers(route: Route, config: HierarchyConfig, params: FilterParams) -> dict[str, Any]:
    """The route's test-part answers, in the map and for the foreign frames, per mode."""
    bank = route.test
    routes = RouteMap.from_metadata(bank.n_db)
    results = bank.results(config)
    profile = bank.profile(config)
    nq, nf = route.n_test, route.n_foreign
    inside, away = np.arange(nq), np.arange(nq, nq + nf)
    return {
        "single": single_answers([results[i] for i in inside], bank.gt[:nq], routes, profile),
        "sequence": sequence_answers(
            results, bank.gt, routes, params, [Drive.along(inside)], profile
        ),
        "foreign_single": single_answers([results[i] for i in away], None, routes, profile),
        "foreign_sequence": sequence_answers(
            results, bank.gt, routes, params, [Drive.along(away)], profile
        ),
    }


def measure(policy: Policy, answers: dict[str, Any], gp: bool) -> dict[str, Any]:
    """The policy on one route's answers (:func:`route_answers`)."""
    out: dict[str, Any] = {}
    for mode in MODES:
        seq = mode == "sequence"
        a = answers[mode]
        rep = apply_acceptance(policy, a, sequence=seq)
        far = apply_acceptance(policy, answers[f"foreign_{mode}"], sequence=seq)
        model = policy.sequence_model if seq else policy.model
        p_far = [x for x in far["p_correct"] if x is not None]
        row: dict[str, Any] = {
            "rule": rep["rule"],
            "threshold": rep["threshold"],
            "n": len(a),
            "right": float(a.correct.mean()),
            "accepted": rep["accepted"],
            "precision": rep["precision"],
            "goal_met": meets(mode, gp, rep["accepted"], rep["precision"]),
            "calibration": calibration(rep["p_correct"], a.correct),
            "foreign": {
                "n": len(answers[f"foreign_{mode}"]),
                "accepted": far["accepted"],
                "mean_p": float(np.mean(p_far)) if p_far else None,
            },
            "feature_auc_test": None if model is None else feature_auc(a, model.features),
            "_p": rep["p_correct"],
        }
        if seq:
            acc = np.array(rep["accepted_answers"], bool)
            row["flips_per_100"] = 100.0 * flips(acc) / len(acc)
            row["recall_at_1"] = float(a.correct.mean())
        out[mode] = row
    return out


def pooled(runs: dict[str, dict[str, Any]], answers: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """ECE of each mode pooled over the routes' test parts: every route, and the Gardens
    Point ones."""
    out: dict[str, Any] = {}
    for mode in MODES:
        groups = (("all", lambda n: True), ("gardens_point", lambda n: n.startswith("gp_")))
        for group, keep in groups:
            p: list[float | None] = []
            c: list[bool] = []
            for name, r in runs.items():
                if keep(name):
                    p += r[mode]["_p"]
                    c += answers[name][mode].correct.tolist()
            cal = calibration(p, np.array(c, bool))
            cal.pop("reliability", None)
            out.setdefault(mode, {})[group] = cal
    return out


# -- output -------------------------------------------------------------------------------------


def _f(x: float | None, fmt: str = ".3f") -> str:
    return "n/a" if x is None else format(x, fmt)


def _yes(x: bool | None) -> str:
    return "" if x is None else ("yes" if x else "no")


def table(report: dict[str, Any]) -> str:
    """Markdown table: per route and models, both modes."""
    lines = [
        "| route (test part) | models | mode | rule | accepted | precision | on-map goal met "
        "| ECE (sampling floor) | flips / 100 | foreign accepted | foreign mean p |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in report["routes"].items():
        for key in ("shipped", "held_out", "no_model"):
            for mode in MODES:
                r = entry[key][mode]
                cal = r["calibration"]
                floor = cal.get("sampling_floor")
                ece = "n/a" if cal["ece"] is None else f"{cal['ece']:.3f} ({floor:.3f})"
                lines.append(
                    f"| {name} ({r['n']}) | {key.replace('_', ' ')} | {mode} | {r['rule']} | "
                    f"{r['accepted']:.3f} | {_f(r['precision'])} | {_yes(r['goal_met'])} | "
                    f"{ece} | {_f(r.get('flips_per_100'), '.1f')} | "
                    f"{r['foreign']['accepted']:.3f} | {_f(r['foreign']['mean_p'])} |"
                )
    return "\n".join(lines)


def pooled_table(report: dict[str, Any]) -> str:
    lines = [
        "| models | mode | routes pooled (test parts) | answers | ECE (sampling floor) | "
        "mean p | right | goal ECE <= 0.05 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key in ("shipped", "held_out"):
        for mode, groups in report["pooled"][key].items():
            for group, cal in groups.items():
                if cal["ece"] is None:
                    continue
                met = _yes(cal["ece"] <= GOAL_ECE) if mode == "sequence" else ""
                lines.append(
                    f"| {key.replace('_', ' ')} | {mode} | {group} | {cal['n']} | "
                    f"{cal['ece']:.3f} ({cal['sampling_floor']:.3f}) | {cal['mean_p']:.3f} | "
                    f"{cal['right']:.3f} | {met} |"
                )
    return "\n".join(lines)


def plot(report: dict[str, Any], out: Path) -> Path | None:
    """Reliability diagram of the test parts: a panel per mode, a line per route, shipped
    models solid, held-out folds dotted (marker area ~ answers in the bin)."""
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(10.4, 4.4), sharey=True)
    for ax, mode in zip(axes, MODES, strict=True):
        ax.plot([0, 1], [0, 1], color="grey", ls="--", lw=1)
        for i, (name, entry) in enumerate(report["routes"].items()):
            for key, style in (("shipped", "-"), ("held_out", ":")):
                cal = entry[key][mode]["calibration"]
                if cal["ece"] is None:
                    continue
                rel = cal["reliability"]
                pred = np.array([np.nan if v is None else v for v in rel["predicted"]])
                obs = np.array([np.nan if v is None else v for v in rel["observed"]])
                count = np.asarray(rel["count"], dtype=np.float64)
                used = count > 0
                ax.plot(
                    pred[used], obs[used], style, color=f"C{i}",
                    label=f"{name} {key.replace('_', ' ')} (ECE {cal['ece']:.3f})",
                )  # fmt: skip
                ax.scatter(
                    pred[used], obs[used], color=f"C{i}", alpha=0.6, zorder=3,
                    s=6 + 300 * count[used] / count.sum(),
                )  # fmt: skip
        ax.set_title(f"{mode}: test parts", fontsize=9)
        ax.set_xlabel("p_correct (the service's)")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="upper left")
    axes[0].set_ylabel("observed share right")
    fig.suptitle(
        f"Reliability, preset {report['preset']!r} ({report['digest'][:12]}): shipped models "
        "solid, leave-one-route-out folds dotted",
        fontsize=9,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def strip(obj: Any) -> Any:
    """``obj`` without the per-answer lists kept for pooling (keys starting with ``_``)."""
    if isinstance(obj, dict):
        return {k: strip(v) for k, v in obj.items() if not str(k).startswith("_")}
    return obj


NOTE = (
    "2 shared CPU cores (other jobs running): the figures do not depend on it, "
    "wall_s does. 100 test queries per Gardens Point protocol: one answer moves a "
    "precision of 99 % by about one point."
)
GOALS = {
    "ece_sequence_pooled": GOAL_ECE,
    "sequence_accepted": GOAL_SEQUENCE,
    "single_accepted_gp": GOAL_SINGLE_GP,
    "foreign_mean_p": GOAL_MEAN_P,
    "flips_per_100": GOAL_FLIPS,
}


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    add_json(ap, "--out", default=str(ROOT / "docs/experiments/acceptance/confidence.json"))
    ap.add_argument(
        "--plot", default=str(ROOT / "docs/experiments/acceptance/reliability_default.png")
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    sets = model_sets(args.config, ROUTES, args.foreign, args.nordland_frames)
    config, params = sets.config, sets.params
    digest = config.digest()
    prov = provenance(args.config, config, args)
    report: dict[str, Any] = {**prov, **report_head(args, sets, NOTE, GOALS), "routes": {}}
    answers: dict[str, dict[str, Any]] = {}
    runs: dict[str, dict[str, dict[str, Any]]] = {"shipped": {}, "held_out": {}}
    for i, route in enumerate(sets.routes):
        gp = route.name.startswith("gp_")
        answers[route.name] = route_answers(route, config, params)
        entry: dict[str, Any] = {"held_out_fit": held_out_fit(sets, i)}
        for key, (policy, models) in route_policies(sets, i).items():
            who = {"preset": args.config, "digest": digest, "models": models}
            entry[key] = {**who, **measure(policy, answers[route.name], gp)}
            if key in runs:
                runs[key][route.name] = entry[key]
        report["routes"][route.name] = entry
        print(f"{route.name} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["pooled"] = {
        "preset": args.config,
        "digest": digest,
        **{key: pooled(runs[key], answers) for key in runs},
    }
    figure = plot(report, Path(args.plot))
    report["figure"] = None if figure is None else str(figure)
    report["wall_s"] = time.perf_counter() - t0
    out = write_record(args.out, strip(report), prov=prov)
    print(f"preset {args.config!r} (digest {digest[:12]}), {report['machine']}")
    print(table(report))
    print()
    print(pooled_table(report))
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
