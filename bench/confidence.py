"""Calibrated confidence on the shared routes: evidence, a logistic model, acceptance.

    python bench/confidence.py [--out results/confidence.json] [--plots DIR]

Each route is split as ``bench/sequence.py`` splits it (alternating stretches of 20 frames;
the default hierarchy on Gardens Point, ``calibrated/nordland_handcrafted`` on Nordland).
For every single-frame answer of both parts, :func:`hmpf.confidence.answer_features`; for
sequence mode, the answers of drives through the :class:`~hmpf.sequence.SequenceFilter`
with the default :class:`~hmpf.sequence.FilterParams` (training part: the traverse at speeds
1, 2 and 3, every offset; test part: the full traverse once, in order), their features with
the estimate.

Reported, everything chosen on the training parts only:

* which features carry information: the ROC AUC of each feature alone (right vs wrong
  answers, training parts pooled; > 0.5: higher means right) and the fitted coefficients;
* the model (:class:`~hmpf.confidence.ConfidenceModel`, l2 = 1) fitted on the four training
  parts pooled and on each route's own; its thresholds for 99 % and 95 % precision are
  chosen on *out-of-fold* predictions of the training part (5 folds of consecutive queries
  per route, each predicted by a model fitted on the other folds), so the threshold does
  not trust the model's in-sample fit;
* a compact feature set chosen on the training parts (greedy forward selection by the
  route-balanced out-of-fold log-loss, :func:`select_features`), evaluated beside all
  features;
* on the test parts: expected calibration error (10 bins; beside it the ECE a perfectly
  calibrated model would show on that many answers), the share of answers accepted
  at each threshold and the precision reached, against today's rule (Combined z >= the
  lowest threshold reaching the target on the training part; in sequence mode posterior
  mass >= the threshold chosen the same way);
* reliability diagrams (PNG) of the test parts;
* the issue's goals, judged on one rule fixed in advance (:data:`PRIMARY_RULE`, selected
  features), beside today's rule.

Runs in about 2 minutes on 2 cores with a warm descriptor cache.
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
from scipy.stats import rankdata

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sequence import ROUTES, load_parts, pyplot  # noqa: E402

from hmpf.confidence import (  # noqa: E402
    FEATURES,
    PROFILE_FEATURES,
    SEQUENCE_FEATURES,
    ConfidenceModel,
    ReferenceProfile,
    expected_calibration_error,
    feature_matrix,
    reliability,
    threshold_for_precision,
)
from hmpf.datasets import dataset_root  # noqa: E402
from hmpf.evaluation.acceptance import Answers, sequence_answers, single_answers  # noqa: E402
from hmpf.evaluation.calibrate import acceptance_threshold  # noqa: E402
from hmpf.evaluation.sequence import Drive, training_drives  # noqa: E402
from hmpf.features import FeatureCache, default_cache_dir  # noqa: E402
from hmpf.runtime import machine_description  # noqa: E402
from hmpf.sequence import FilterParams, RouteMap  # noqa: E402

TARGETS = (0.99, 0.95)
FOLDS = 5
L2 = 1.0
#: The issue's goals (accepted at 99 % precision on the test part).
GOALS_SINGLE = {"gp_dl_dr": 0.40, "gp_dl_nr": 0.25, "gp_dr_nr": 0.25, "nordland_s_w": 0.20}
GOAL_SEQUENCE_GP = 0.80
GOAL_ECE = 0.05
#: The rule the goals are judged on, fixed before looking at the test parts: one model for
#: every route (route-balanced), each route's threshold from its own training part.
PRIMARY_RULE = "pooled model, route threshold"


# -- the answers and their features -------------------------------------------------------------


def _rows(answers: Answers) -> dict[str, Any]:
    """A part's answers as the tables below read them."""
    return {
        "features": answers.features,
        "correct": answers.correct,
        "score": answers.score,
        "query": answers.query,
    }


def single_rows(
    results: Sequence[Any], gt: np.ndarray, profile: ReferenceProfile | None = None
) -> dict[str, Any]:
    """Features, correctness and quality of every single-frame answer of one part."""
    return _rows(single_answers(results, gt, RouteMap.from_metadata(gt.shape[1]), profile))


def sequence_rows(
    results: Sequence[Any],
    gt: np.ndarray,
    drives: Sequence[Drive],
    params: FilterParams,
    profile: ReferenceProfile | None = None,
) -> dict[str, Any]:
    """Features (with the estimate), correctness and mass of every answer of ``drives``."""
    routes = RouteMap.from_metadata(gt.shape[1])
    return _rows(sequence_answers(results, gt, routes, params, drives, profile))


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
    rng = np.random.default_rng(seed)
    return float(
        np.mean([expected_calibration_error(p, rng.random(len(p)) < p) for _ in range(draws)])
    )


def accepted_at(score: np.ndarray, correct: np.ndarray, threshold: float) -> dict[str, float]:
    acc = np.asarray(score) >= threshold
    n = int(acc.sum())
    return {
        "threshold": float(threshold),
        "accepted": float(acc.mean()) if len(acc) else 0.0,
        "precision": float(correct[acc].mean()) if n else 1.0,
        "n_accepted": n,
    }


def out_of_fold(
    X: np.ndarray,
    y: np.ndarray,
    groups: np.ndarray,
    names: Sequence[str],
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Predictions of each training answer by a model fitted without its fold (``groups``:
    the fold of each answer)."""
    p = np.empty(len(y))
    for g in np.unique(groups):
        hold = groups == g
        w = None if weights is None else weights[~hold]
        model = ConfidenceModel.fit(X[~hold], y[~hold], names, l2=L2, sample_weight=w)
        p[hold] = model.predict(X[hold])
    return p


def log_loss(p: np.ndarray, y: np.ndarray, weights: np.ndarray) -> float:
    p = np.clip(p, 1e-12, 1 - 1e-12)
    return float(np.average(-(y * np.log(p) + (1 - y) * np.log(1 - p)), weights=weights))


def select_features(
    X: np.ndarray, y: np.ndarray, groups: np.ndarray, weights: np.ndarray, names: Sequence[str]
) -> tuple[list[str], list[dict[str, Any]]]:
    """Greedy forward selection on the pooled training parts: add the feature that lowers
    the route-balanced out-of-fold log-loss most, while it lowers it by >= 0.001."""
    chosen: list[int] = []
    steps: list[dict[str, Any]] = []
    current = log_loss(np.full(len(y), np.average(y, weights=weights)), y, weights)
    while len(chosen) < len(names):
        trials = {}
        for j in range(len(names)):
            if j in chosen:
                continue
            cols = [*chosen, j]
            sub = [names[c] for c in cols]
            trials[j] = log_loss(out_of_fold(X[:, cols], y, groups, sub, weights), y, weights)
        j = min(trials, key=lambda k: trials[k])
        if current - trials[j] < 1e-3:
            break
        chosen.append(j)
        current = trials[j]
        steps.append({"add": names[j], "oof_log_loss": current})
    return [names[c] for c in chosen], steps


def folds_of(query: np.ndarray, nq: int, offset: int = 0) -> np.ndarray:
    """Fold of each answer: ``FOLDS`` stretches of consecutive queries (plus ``offset``, so
    routes pooled keep their folds apart)."""
    return offset + np.minimum(query * FOLDS // max(nq, 1), FOLDS - 1)


# -- one mode (single frame or sequence) --------------------------------------------------------


def pooled_training(
    data: dict[str, dict[str, dict[str, Any]]], names: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The training parts pooled: features, labels, folds (5 per route) and route-balanced
    weights (each route weighs as much as the others: Nordland has 18x the answers of a
    Gardens Point part)."""
    X, y, g, w = [], [], [], []
    for i, r in enumerate(data):
        rows = data[r]["train"]
        X.append(feature_matrix(rows["features"], names))
        y.append(rows["correct"])
        g.append(folds_of(rows["query"], int(rows["query"].max()) + 1, 10 * i))
        w.append(np.full(len(rows["correct"]), 1 / len(rows["correct"])))
    weights = np.concatenate(w)
    return (
        np.vstack(X),
        np.concatenate(y),
        np.concatenate(g),
        weights * len(weights) / weights.sum(),
    )


def evaluate_mode(
    data: dict[str, dict[str, dict[str, Any]]], names: Sequence[str], today: str
) -> dict[str, Any]:
    """Feature AUCs, pooled and per-route models and their test figures for one mode.

    ``data[route]["train" | "test"]`` are rows as :func:`single_rows` makes them; ``today``
    names the score of today's rule (the Combined z, or the posterior mass).
    """
    routes = list(data)
    mats = {
        r: {part: feature_matrix(data[r][part]["features"], names) for part in ("train", "test")}
        for r in routes
    }
    ys = {r: {part: data[r][part]["correct"] for part in ("train", "test")} for r in routes}
    X_all, y_all, g_all, w_all = pooled_training(data, names)
    groups = {
        r: folds_of(data[r]["train"]["query"], int(data[r]["train"]["query"].max()) + 1)
        for r in routes
    }
    feature_auc = {
        "pooled": {n: auc(X_all[:, j], y_all) for j, n in enumerate(names)},
        **{
            r: {n: auc(mats[r]["train"][:, j], ys[r]["train"]) for j, n in enumerate(names)}
            for r in routes
        },
    }
    pooled = ConfidenceModel.fit(X_all, y_all, names, l2=L2, sample_weight=w_all)
    oof_pooled = out_of_fold(X_all, y_all, g_all, names, w_all)
    pooled_thr = {t: threshold_for_precision(oof_pooled, y_all, t) for t in TARGETS}
    out: dict[str, Any] = {
        "features": list(names),
        "feature_auc_train": feature_auc,
        "models": {"pooled": pooled.to_dict()},
        "routes": {},
    }
    start = 0
    for r in routes:
        Xtr, ytr, Xte, yte = mats[r]["train"], ys[r]["train"], mats[r]["test"], ys[r]["test"]
        own = ConfidenceModel.fit(Xtr, ytr, names, l2=L2)
        out["models"][r] = own.to_dict()
        oof_own = out_of_fold(Xtr, ytr, groups[r], names)
        oof_pool_r = oof_pooled[start : start + len(ytr)]
        start += len(ytr)
        p_pool, p_own = pooled.predict(Xte), own.predict(Xte)
        score_tr, score_te = data[r]["train"]["score"], data[r]["test"]["score"]
        row: dict[str, Any] = {
            "n_train": len(ytr),
            "n_test": len(yte),
            "right_train": float(ytr.mean()),
            "right_test": float(yte.mean()),
            "ece": {
                "pooled": expected_calibration_error(p_pool, yte),
                "per_route": expected_calibration_error(p_own, yte),
                "sampling_floor": ece_floor(p_pool),
            },
            "reliability": {
                k: {
                    f: np.where(np.isnan(v), None, v).tolist() if f != "count" else v.tolist()
                    for f, v in vars(reliability(p, yte)).items()
                }
                for k, p in (("pooled", p_pool), ("per_route", p_own))
            },
            "accept": {},
        }
        for t in TARGETS:
            z_thr = acceptance_threshold(score_tr, ytr, t)["threshold"]
            row["accept"][f"{t:g}"] = {
                f"today ({today})": accepted_at(np.nan_to_num(score_te, nan=-np.inf), yte, z_thr),
                "pooled model, one threshold": accepted_at(p_pool, yte, pooled_thr[t]),
                "pooled model, route threshold": accepted_at(
                    p_pool, yte, threshold_for_precision(oof_pool_r, ytr, t)
                ),
                "per-route model": accepted_at(
                    p_own, yte, threshold_for_precision(oof_own, ytr, t)
                ),
            }
        row["_p"] = {"pooled": p_pool, "per_route": p_own, "correct": yte}
        out["routes"][r] = row
    return out


# -- output -------------------------------------------------------------------------------------


def auc_table(mode: dict[str, Any]) -> str:
    names = mode["features"]
    cols = list(mode["feature_auc_train"])
    pooled = mode["models"]["pooled"]
    lines = [
        "| feature | " + " | ".join(f"AUC {c}" for c in cols) + " | pooled coef |",
        "|---|" + "---|" * (len(cols) + 1),
    ]
    for j, n in enumerate(names):
        aucs = " | ".join(f"{mode['feature_auc_train'][c][n]:.3f}" for c in cols)
        lines.append(f"| {n} | {aucs} | {pooled['coef'][j]:+.3f} |")
    lines.append(f"| (intercept) |{' |' * len(cols)} {pooled['intercept']:+.3f} |")
    return "\n".join(lines)


def accept_table(mode: dict[str, Any]) -> str:
    lines = [
        "| route (test part) | right | ECE pooled / per route (sampling floor) | rule "
        "| accepted @99 % (precision) | accepted @95 % (precision) |",
        "|---|---|---|---|---|---|",
    ]
    for r, row in mode["routes"].items():
        rules = list(row["accept"]["0.99"])
        for i, rule in enumerate(rules):
            a99, a95 = row["accept"]["0.99"][rule], row["accept"]["0.95"][rule]
            head = (
                f"| {r} ({row['n_test']}) | {row['right_test']:.3f} | "
                f"{row['ece']['pooled']:.3f} / {row['ece']['per_route']:.3f} "
                f"({row['ece']['sampling_floor']:.3f}) "
                if i == 0
                else "| | | "
            )
            lines.append(
                f"{head}| {rule} | {a99['accepted']:.3f} ({a99['precision']:.3f}) | "
                f"{a95['accepted']:.3f} ({a95['precision']:.3f}) |"
            )
    return "\n".join(lines)


def goals_table(modes: dict[str, dict[str, Any]]) -> str:
    """The issue's goals for the rule fixed in advance (:data:`PRIMARY_RULE` with the
    features selected on the training parts), beside today's rule."""
    lines = [
        f"| goal (test part) | target | {PRIMARY_RULE}, selected features | today's rule | met |",
        "|---|---|---|---|---|",
    ]

    def cell(x: dict[str, float]) -> str:
        return f"{x['accepted']:.3f} (precision {x['precision']:.3f})"

    checks = [("single frame", r, g) for r, g in GOALS_SINGLE.items()]
    checks += [("sequence", r, GOAL_SEQUENCE_GP) for r in GOALS_SINGLE if r.startswith("gp_")]
    for mode_name, r, goal in checks:
        acc = modes[f"{mode_name}, selected features"]["routes"][r]["accept"]["0.99"]
        ours = acc[PRIMARY_RULE]
        today = next(v for k, v in acc.items() if k.startswith("today"))
        met = ours["accepted"] >= goal and ours["precision"] >= 0.99
        lines.append(
            f"| {mode_name} {r}: accepted @99 % | >= {goal:.2f} | {cell(ours)} | "
            f"{cell(today)} | {'yes' if met else 'no'} |"
        )
    for mode_name in ("single frame", "sequence"):
        for r, row in modes[f"{mode_name}, selected features"]["routes"].items():
            e = row["ece"]["pooled"]
            lines.append(
                f"| {mode_name} {r}: ECE | <= {GOAL_ECE:.2f} | {e:.3f} (sampling floor "
                f"{row['ece']['sampling_floor']:.3f}) | | {'yes' if e <= GOAL_ECE else 'no'} |"
            )
    return "\n".join(lines)


def plot(modes: dict[str, dict[str, Any]], out: Path) -> list[Path]:
    """One reliability diagram per mode: a panel per route, pooled and per-route models."""
    plt = pyplot()
    if plt is None:
        return []
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for mode_name, mode in modes.items():
        rows = mode["routes"]
        fig, axes = plt.subplots(1, len(rows), figsize=(3.6 * len(rows), 3.8), sharey=True)
        for ax, (r, row) in zip(np.atleast_1d(axes), rows.items(), strict=True):
            ax.plot([0, 1], [0, 1], color="grey", ls="--", lw=1)
            for key, style, colour in (("pooled", "-", "C0"), ("per_route", ":", "C1")):
                rel = reliability(row["_p"][key], row["_p"]["correct"])
                used = rel.count > 0
                ax.plot(
                    rel.predicted[used],
                    rel.observed[used],
                    style,
                    color=colour,
                    label=f"{key.replace('_', ' ')} (ECE {row['ece'][key]:.3f})",
                )
                # Marker area in proportion to the bin's answers (a sparse bin says little).
                ax.scatter(
                    rel.predicted[used],
                    rel.observed[used],
                    s=6 + 300 * rel.count[used] / rel.count.sum(),
                    color=colour,
                    alpha=0.7,
                    zorder=3,
                )
            ax.set_title(f"{r} ({row['n_test']} answers)", fontsize=9)
            ax.set_xlabel("predicted p_correct")
            ax.set_xlim(0, 1)
            ax.set_ylim(0, 1.02)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper left")
        np.atleast_1d(axes)[0].set_ylabel("observed share right (test part)")
        fig.suptitle(
            f"Reliability, {mode_name} (test parts; 10 bins, marker area ~ answers in the bin)",
            fontsize=10,
        )
        fig.tight_layout()
        slug = mode_name.replace(",", "").replace(" ", "_")
        path = out / f"reliability_{slug}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def strip(mode: dict[str, Any]) -> dict[str, Any]:
    """``mode`` without the arrays kept for plotting."""
    return {
        **mode,
        "routes": {
            r: {k: v for k, v in row.items() if k != "_p"} for r, row in mode["routes"].items()
        },
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default=str(dataset_root()))
    ap.add_argument("--cache-dir", default=str(default_cache_dir()))
    ap.add_argument("--out", default=str(ROOT / "results" / "confidence.json"))
    ap.add_argument("--plots", default=str(ROOT / "docs" / "experiments" / "confidence"))
    args = ap.parse_args()

    t0 = time.perf_counter()
    parts = load_parts(Path(args.datasets), FeatureCache(args.cache_dir))
    params = FilterParams()
    single: dict[str, dict[str, Any]] = {}
    seq: dict[str, dict[str, Any]] = {}
    for name, p in parts.items():
        single[name] = {
            part: single_rows(*p[part], p[f"{part}_profile"]) for part in ("train", "test")
        }
        tr_results, tr_gt = p["train"]
        te_results, te_gt = p["test"]
        seq[name] = {
            "train": sequence_rows(
                tr_results, tr_gt, training_drives(len(tr_results)), params, p["train_profile"]
            ),
            "test": sequence_rows(
                te_results,
                te_gt,
                [Drive.along(np.arange(len(te_results)))],
                params,
                p["test_profile"],
            ),
        }
        print(f"{name}: features done ({time.perf_counter() - t0:.0f} s)", flush=True)
    modes: dict[str, dict[str, Any]] = {}
    selection: dict[str, Any] = {}
    for mode_name, data, names, today in (
        ("single frame", single, (*FEATURES, "ref_z"), "Combined z"),
        ("sequence", seq, FEATURES + SEQUENCE_FEATURES + PROFILE_FEATURES, "posterior mass"),
    ):
        modes[f"{mode_name}, all features"] = evaluate_mode(data, names, today)
        X, y, g, w = pooled_training(data, names)
        chosen, steps = select_features(X, y, g, w, names)
        selection[mode_name] = steps
        print(f"{mode_name}: features selected on the training parts: {steps}", flush=True)
        modes[f"{mode_name}, selected features"] = evaluate_mode(data, chosen, today)
    figures = plot(modes, Path(args.plots))
    print(f"\nMachine: {machine_description()}; {time.perf_counter() - t0:.0f} s")
    for mode_name, mode in modes.items():
        print(f"\n### {mode_name}: features on the training parts (AUC alone; pooled model)\n")
        print(auc_table(mode))
        print(f"\n### {mode_name}: test parts\n")
        print(accept_table(mode))
    print("\n### goals (issue 17; the rule fixed in advance, features selected on training)\n")
    print(goals_table(modes))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(
        json.dumps(
            {
                "machine": machine_description(),
                "configs": {r: cfg for r, (_, _, cfg) in ROUTES.items()},
                "filter": "FilterParams() defaults",
                "l2": L2,
                "folds": FOLDS,
                "selection": selection,
                "modes": {k: strip(v) for k, v in modes.items()},
                "figures": [str(f) for f in figures],
            },
            indent=1,
        )
    )
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
