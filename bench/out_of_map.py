"""Places that are not in the map: how often are queries from elsewhere accepted, and what
does refusing them cost on the map's own queries?

    python bench/out_of_map.py [--foreign 200] [--maps gp_dr_nr,...] [--out results/out_of_map.json]

Each map is the *training part* of a route (the three Gardens Point protocols with the
default hierarchy, Nordland summer -> winter with ``calibrated/nordland_handcrafted``),
split as ``hmpf-calibrate`` splits it (alternating stretches of 20 frames). On that training
part, as ``hmpf-calibrate --sequence`` does (:mod:`hmpf.evaluation.acceptance`), for each of
:data:`VARIANTS` the single-frame confidence model and its threshold for 99 % precision
(out-of-fold) and the sequence model on the training drives (speeds 1, 2, 3, default
:class:`~hmpf.sequence.FilterParams`) with its threshold; beside them today's rules, the z
threshold (Combined z) and the posterior-mass threshold (each the lowest value giving 99 %
on the training answers).

Then two sets of queries the map does not cover, each answered against the map:

* ``foreign``: ``--foreign`` frames of another route spread evenly over it (Nordland winter
  thumbnails against a Gardens Point map, Gardens Point night_right frames against the
  Nordland map), through the same extraction;
* ``removed``: the route's test-part queries against the training part's references, i.e.
  the map with the queries' own references removed. Queries whose +-2-frame ground truth
  still reaches a training reference (the two frames either side of each join of the
  20-frame stretches) are left out: for them the place *is* in the map.

Single frame: each answer accepted by a model (``p_correct >= threshold``) or by the z
rule. Sequence mode: the queries driven in order as one vehicle through the filter (every
frame counts), accepted by a model or by the posterior mass. A false accept is an accepted
answer to an out-of-map query; the goal of issue 17 is <= 1 %.

And in the map: each rule on the route's test part against its own references (single
frame; sequence mode driven once, in order): accepted share at the 99 % threshold, the
precision reached and, for the models, the expected calibration error.

Writes the JSON report and prints two Markdown tables.
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
sys.path.insert(0, str(ROOT / "bench"))

from sequence import ROUTES, pyplot  # noqa: E402

from hmpf.confidence import (  # noqa: E402
    ConfidenceModel,
    expected_calibration_error,
    feature_matrix,
    reliability,
)
from hmpf.config import load_config  # noqa: E402
from hmpf.datasets import dataset_root, list_images  # noqa: E402
from hmpf.evaluation.acceptance import (  # noqa: E402
    SEQUENCE_MODEL_FEATURES,
    SINGLE_FEATURES,
    Answers,
    fit_acceptance,
    outside_answers,
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

#: The foreign route whose frames each map is asked about.
FOREIGN = {
    **{k: "nordland_64x32/winter" for k in ROUTES if k.startswith("gp_")},
    "nordland_s_w": "gardens_point/night_right",
}
#: Map name -> (reference folder, query folder, config, the foreign route's frames): the
#: routes of ``bench/sequence.py``.
MAPS = {k: (*ROUTES[k], FOREIGN[k]) for k in ROUTES}
TARGET = 0.99
#: The lower target the shipped model is also reported at (variant :data:`LOW`).
TARGET_LOW = 0.95
LOW = "absolute, 95 %"
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


#: The models compared: ``relative`` (the features of the first model, every one relative to
#: the map; trained on in-map answers only) and ``absolute`` (what ``hmpf-calibrate`` now
#: fits: with the absolute evidence ``ref_z`` / ``sequence_ref_z`` and trained with the
#: training part's own out-of-map answers, :func:`outside_answers`).
VARIANTS = {
    "relative": (
        ("tier1_margin", "agreement", "quality"),
        ("sequence_logit", "sequence_agrees", "tier1_rank"),
        False,
    ),
    "absolute": (SINGLE_FEATURES, SEQUENCE_MODEL_FEATURES, True),
}


def fit_map(train: ScoreBank, config: Any, params: FilterParams) -> dict[str, Any]:
    """Models and thresholds of one map, on its training part (as ``hmpf-calibrate``), for
    each of :data:`VARIANTS`; the z and posterior-mass thresholds."""
    routes = RouteMap.from_metadata(train.n_db)
    results = train.results(config)
    profile = train.profile(config)
    single = single_answers(results, train.gt, routes, profile)
    seq = sequence_answers(
        results, train.gt, routes, params, training_drives(train.n_query), profile
    )
    out_single, out_seq = outside_answers(train, config, profile, params)
    z = acceptance_threshold(single.score, single.correct, TARGET)
    mass = acceptance_threshold(seq.score, seq.correct, TARGET)
    fitted: dict[str, Any] = {
        "z": z["threshold"],
        "mass": mass["threshold"],
        "profile": profile,
        "train": {"z": z, "mass": mass, "n_outside": len(out_single)},
        "variants": {},
    }
    for name, (s_names, q_names, with_outside) in VARIANTS.items():
        model, thr, figs = fit_acceptance(
            single, s_names, TARGET, out_single if with_outside else None
        )
        smodel, sthr, sfigs = fit_acceptance(
            seq, q_names, TARGET, out_seq if with_outside else None
        )
        fitted["variants"][name] = {
            "model": model,
            "threshold": thr,
            "sequence_model": smodel,
            "sequence_threshold": sthr,
        }
        fitted["train"][name] = {"single": figs, "sequence": sfigs}
    # The shipped model at the lower target too (the same fit, another threshold; the
    # out-of-map bound then 1 - 0.95).
    s_names, q_names, _ = VARIANTS["absolute"]
    low = {}
    for key, answers, names, out in (
        ("", single, s_names, out_single),
        ("sequence_", seq, q_names, out_seq),
    ):
        m, t, f = fit_acceptance(answers, names, TARGET_LOW, out)
        low |= {f"{key}model": m, f"{key}threshold": t}
        fitted["train"].setdefault(LOW, {})[key or "single"] = f
    fitted["variants"][LOW] = low
    return fitted


def decisions(
    fitted: dict[str, Any], single: Answers, seq: Answers
) -> list[tuple[str, str, float, np.ndarray]]:
    """(mode, rule, threshold, accepted) of every rule on one query set: each variant's
    models, the z rule and the posterior-mass rule."""

    def p(model: ConfidenceModel, a: Answers) -> np.ndarray:
        return np.asarray(model.predict(feature_matrix(a.features, model.features)))

    out = []
    for name, v in fitted["variants"].items():
        out.append(
            ("single", f"model ({name})", v["threshold"], p(v["model"], single) >= v["threshold"])
        )
        out.append(
            (
                "sequence",
                f"model ({name})",
                v["sequence_threshold"],
                p(v["sequence_model"], seq) >= v["sequence_threshold"],
            )
        )
    out.append(
        ("single", "z", fitted["z"], np.nan_to_num(single.score, nan=-np.inf) >= fitted["z"])
    )
    out.append(
        (
            "sequence",
            "mass",
            fitted["mass"],
            np.nan_to_num(seq.score, nan=-np.inf) >= fitted["mass"],
        )
    )
    return sorted(out, key=lambda r: r[0])


def in_map_row(
    name: str,
    mode: str,
    rule: str,
    thr: float,
    acc: np.ndarray,
    correct: np.ndarray,
    ece: float | None = None,
) -> dict[str, Any]:
    """Accepted share and precision of one rule on the map's own (in-map) test part (and a
    model's expected calibration error there)."""
    n = int(acc.sum())
    return {
        "ece": ece,
        "map": name,
        "mode": mode,
        "rule": rule,
        "threshold": float(thr),
        "n": int(len(acc)),
        "accepted": float(acc.mean()),
        "precision": float(correct[acc].mean()) if n else None,
    }


def in_map_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of the in-map test-part figures."""
    lines = [
        "| route (test part) | mode | rule | threshold | accepted | precision | ECE |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        prec = "n/a" if r["precision"] is None else f"{r['precision']:.3f}"
        lines.append(
            f"| {r['map']} ({r['n']}) | {r['mode']} | {r['rule']} | {r['threshold']:.4g} | "
            f"{r['accepted']:.3f} | {prec} | "
            f"{'' if r['ece'] is None else format(r['ece'], '.3f')} |"
        )
    return "\n".join(lines)


def plot(curves: dict[str, dict[str, dict[str, Any]]], out: Path) -> Path | None:
    """Reliability of the per-route models on the routes' test parts: a panel per mode
    (single frame, sequence), a line per route and variant (``curves[mode][label]`` holds
    ``p`` and ``correct``). None when matplotlib is missing."""
    plt = pyplot()
    if plt is None:
        return None
    fig, axes = plt.subplots(1, len(curves), figsize=(5.2 * len(curves), 4.4), sharey=True)
    for ax, (mode, lines) in zip(np.atleast_1d(axes), curves.items(), strict=True):
        ax.plot([0, 1], [0, 1], color="grey", ls="--", lw=1)
        for i, (label, c) in enumerate(lines.items()):
            rel = reliability(c["p"], c["correct"])
            used = rel.count > 0
            style = "-" if "absolute" in label else ":"
            colour = f"C{i // 2}"
            ece = expected_calibration_error(c["p"], c["correct"])
            ax.plot(
                rel.predicted[used], rel.observed[used], style, color=colour,
                label=f"{label} (ECE {ece:.3f})",
            )  # fmt: skip
            ax.scatter(
                rel.predicted[used], rel.observed[used], color=colour, alpha=0.7, zorder=3,
                s=6 + 300 * rel.count[used] / rel.count.sum(),
            )  # fmt: skip
        ax.set_title(f"{mode}: per-route models, test parts", fontsize=9)
        ax.set_xlabel("predicted p_correct")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="upper left")
    np.atleast_1d(axes)[0].set_ylabel("observed share right")
    fig.suptitle(
        "Reliability of hmpf-calibrate's models (solid: absolute evidence + out-of-map "
        "training, dotted: relative only; marker area ~ answers in the bin)",
        fontsize=9,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--foreign", type=int, default=200, help="frames of the foreign route")
    ap.add_argument("--maps", default=",".join(MAPS), help="maps to test (comma-separated)")
    ap.add_argument("--out", default=str(ROOT / "results" / "out_of_map.json"))
    ap.add_argument(
        "--plot",
        default=str(ROOT / "docs" / "experiments" / "confidence" / "reliability_calibrated.png"),
        help="reliability diagram of the per-route models (PNG)",
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    datasets = dataset_root()
    cache = FeatureCache(default_cache_dir())
    params = FilterParams()
    rows: list[dict[str, Any]] = []
    in_map: list[dict[str, Any]] = []
    curves: dict[str, dict[str, dict[str, Any]]] = {}
    maps: dict[str, Any] = {}
    for name in args.maps.split(","):
        ref, qry, cfg_name, foreign_dir = MAPS[name]
        config = load_config(cfg_name)
        frames = list_images(datasets / foreign_dir)
        foreign = [frames[i] for i in spread(len(frames), args.foreign)]
        data = EvalData.frames(datasets / ref, datasets / qry, TOLERANCE)
        train_data, test_data = split_data(data, block=BLOCK)
        train = ScoreBank.build(config, train_data, cache=cache)
        fitted = fit_map(train, config, params)
        r_train, _ = block_parts(len(data.reference))
        _, q_test = block_parts(len(data.query))
        outside = out_of_map(data.gt, q_test, r_train)
        query_sets = {
            "foreign": (foreign, np.ones(len(foreign), dtype=bool)),
            "removed": (test_data.query, outside),
        }
        maps[name] = {
            "config": cfg_name,
            "foreign": foreign_dir,
            "n_reference": train.n_db,
            "thresholds": {
                "z": fitted["z"],
                "mass": fitted["mass"],
                **{
                    f"{v}_{k}": float(f[k])
                    for v, f in fitted["variants"].items()
                    for k in ("threshold", "sequence_threshold")
                },
            },
            "train": fitted["train"],
            "models": {
                v: {"single": f["model"].to_dict(), "sequence": f["sequence_model"].to_dict()}
                for v, f in fitted["variants"].items()
            },
        }
        # The map's own test part (in the map): what each rule still accepts.
        test = ScoreBank.build(config, test_data, cache=cache)
        t_results = test.results(config)
        t_routes = RouteMap.from_metadata(test.n_db)
        t_prof = test.profile(config)
        t_single = single_answers(t_results, test.gt, t_routes, t_prof)
        t_seq = sequence_answers(t_results, test.gt, t_routes, params, profile=t_prof)
        eces = {}
        for v, f in fitted["variants"].items():
            for mode, key, ans in (
                ("single", "model", t_single),
                ("sequence", "sequence_model", t_seq),
            ):
                p = f[key].predict(feature_matrix(ans.features, f[key].features))
                eces[(mode, f"model ({v})")] = expected_calibration_error(p, ans.correct)
                if v != LOW:  # the same model as "absolute", another threshold
                    curves.setdefault(mode, {})[f"{name} {v}"] = {"p": p, "correct": ans.correct}
        for mode, rule, thr, acc in decisions(fitted, t_single, t_seq):
            correct = t_single.correct if mode == "single" else t_seq.correct
            ece = eces.get((mode, rule))
            in_map.append(in_map_row(name, mode, rule, thr, acc, correct, ece))
        for qname, (queries, out_mask) in query_sets.items():
            gt = np.zeros((len(queries), train.n_db), dtype=bool)
            bank = ScoreBank.build(
                config, EvalData(train_data.reference, list(queries), gt, "none"), cache=cache
            )
            results = bank.results(config)
            routes = RouteMap.from_metadata(bank.n_db)
            prof = fitted["profile"]
            single = single_answers(results, None, routes, prof)
            seq = sequence_answers(results, None, routes, params, profile=prof)
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
        "foreign_frames": args.foreign,
        "filter": vars(params) if hasattr(params, "__dict__") else str(params),
        "maps": maps,
        "rows": rows,
        "in_map": in_map,
        "wall_s": time.perf_counter() - t0,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=str))
    figure = plot(curves, Path(args.plot))
    if figure is not None:
        report["figure"] = str(figure)
        out.write_text(json.dumps(report, indent=1, default=str))
    print(table(rows))
    print()
    print(in_map_table(in_map))
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
