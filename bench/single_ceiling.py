"""How much of a route single frames can be accepted at 99 % precision: the evidence's ceiling.

    python -m bench.single_ceiling [--config default] [--foreign 200] [--nordland-frames 800]
        [--out docs/experiments/acceptance/single_ceiling.json]

The shipped single-frame model accepts 5-7 % of the night answers on Gardens Point, at
precision 1.000 (goal: 30 % at 99 %). Is that its threshold (one number for every route,
chosen on the training parts pooled) or the evidence? For each route of
``bench/shipped_acceptance.py``, on its test part and its whole traverse, this measures the
**ceiling**: the largest share of the route's single-frame answers that any threshold on a
score accepts at 99 % precision, the threshold chosen *knowing the answers* (an upper bound
no rule chosen beforehand can beat: :func:`ceiling`). The scores:

* ``p_correct`` of the shipped models and of the held-out fold's (fitted on the other
  routes, as in ``bench/shipped_acceptance.py``);
* **geometric verification** of the answer, evidence the model does not read: the inliers
  of a homography fitted robustly between the query's KAZE features and the answered
  reference's (the ``inliers`` method's default settings, :class:`hmpf.methods.inliers.Inliers`),
  whether a verifier in the hierarchy or in the model could lift the ceiling.

Beside each ceiling, what the models accept at their own thresholds and the medians of the
inliers of right and wrong answers. Writes the JSON record (preset, digest, machine, date,
commit) and prints a Markdown table.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.shipped_acceptance import (
    ROUTES,
    TARGET,
    Route,
    add_route_arguments,
    model_sets,
)
from hmpf.acceptance import Policy
from hmpf.evaluation.acceptance import apply_acceptance, sequence_answers, single_answers
from hmpf.evaluation.sequence import Drive
from hmpf.imageio import load_image
from hmpf.methods.inliers import Inliers
from hmpf.methods.kaze import KazeFeatures
from hmpf.sequence import FilterParams, RouteMap

__all__ = ["ceiling", "median_of"]


def ceiling(score: np.ndarray, correct: np.ndarray, target: float = TARGET) -> tuple[float, Any]:
    """The largest share of answers that a threshold ``t`` on ``score`` (accepting every
    answer with ``score >= t``; a NaN score is never accepted) accepts at precision >=
    ``target``, and that threshold (None when none does: share 0)."""
    s = np.asarray(score, dtype=np.float64)
    y = np.asarray(correct, dtype=bool)
    if s.shape != y.shape:
        raise ValueError("score and correct differ in length")
    n = len(s)
    keep = ~np.isnan(s)
    s, y = s[keep], y[keep]
    if not len(s):
        return 0.0, None
    order = np.argsort(-s, kind="stable")
    ss, yy = s[order], y[order]
    precision = np.cumsum(yy) / np.arange(1, len(ss) + 1)
    # A threshold accepts every answer tied with the last one it accepts: cut at tie ends.
    ends = np.r_[ss[1:] != ss[:-1], True]
    ok = np.flatnonzero(ends & (precision >= target))
    if not len(ok):
        return 0.0, None
    i = int(ok.max())
    return (i + 1) / n, float(ss[i])


def median_of(x: np.ndarray) -> float | None:
    return float(np.median(x)) if len(x) else None


class Verifier:
    """KAZE features per image (extracted once) and the inliers of a query / reference
    pair."""

    def __init__(self) -> None:
        self.method = Inliers()
        self._features: dict[str, KazeFeatures] = {}

    def features(self, path: str) -> KazeFeatures:
        if path not in self._features:
            self._features[path] = self.method.extract(load_image(path))
        return self._features[path]

    def inliers(self, query: str, reference: str) -> int:
        return self.method.pair_inliers(self.features(query), self.features(reference))


def _model(policy: Policy, answers: Any, sequence: bool = False) -> dict[str, Any]:
    rep = apply_acceptance(policy, answers, sequence=sequence)
    p = np.array([np.nan if x is None else x for x in rep["p_correct"]], dtype=np.float64)
    share, thr = ceiling(p, answers.correct)
    return {
        "threshold": policy.sequence_threshold if sequence else policy.model_threshold,
        "accepted": rep["accepted"],
        "precision": rep["precision"],
        "ceiling": share,
        "ceiling_threshold": thr,
    }


def part(
    route: Route,
    which: str,
    policies: dict[str, Policy],
    verifier: Verifier,
    params: FilterParams,
) -> dict[str, Any]:
    """Route ``route``'s single-frame answers on its ``test`` part or ``whole`` traverse:
    each model's acceptance and ceiling, and the inliers' ceiling; and the same drive in
    sequence mode (``params``' filter): its recall@1 and each sequence model's acceptance
    (with the stay threshold) and ceiling (its ``p_correct`` frame by frame)."""
    if which == "test":
        bank, nq = route.test, route.n_test
        data = route.test_data
        results = bank.results(route.config)[:nq]
        profile = bank.profile(route.config)
    else:
        bank, data = route.whole(), route.data
        results, profile = route.whole_results()
        nq = len(results)
    routes = RouteMap.from_metadata(bank.n_db)
    answers = single_answers(results, bank.gt[:nq], routes, profile)
    y = answers.correct
    n = np.array(
        [
            verifier.inliers(str(data.query[i]), str(data.reference[int(r.match)]))
            if int(r.match) >= 0
            else 0
            for i, r in enumerate(results)
        ],
        dtype=np.float64,
    )
    share, thr = ceiling(n, y)
    drive = [Drive.along(np.arange(nq))]
    seq = sequence_answers(results, bank.gt[:nq], routes, params, drive, profile)
    return {
        "n": int(nq),
        "right": float(y.mean()),
        "models": {k: _model(p, answers) for k, p in policies.items()},
        "inliers": {
            "ceiling": share,
            "ceiling_threshold": thr,
            "median_right": median_of(n[y]),
            "median_wrong": median_of(n[~y]),
            "max_wrong": float(n[~y].max()) if (~y).any() else None,
        },
        "sequence": {
            "right": float(seq.correct.mean()),
            "models": {k: _model(p, seq, sequence=True) for k, p in policies.items()},
        },
    }


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f} %"


def _accepted(m: dict[str, Any]) -> str:
    prec = m["precision"]
    return f"{_pct(m['accepted'])} ({'n/a' if prec is None else f'{prec:.3f}'})"


def _model_cells(m: dict[str, Any]) -> str:
    """The shipped and held-out models' cells: accepted (precision) and ceiling, each."""
    return " | ".join(
        f"{_accepted(m[k])} | {_pct(m[k]['ceiling'])}" for k in ("shipped", "held_out")
    )


def table(report: dict[str, Any]) -> str:
    """Markdown: single frame, a row per route and part."""
    lines = [
        "| route | part | answers right | shipped: accepted (precision) | ceiling, shipped "
        "p_correct | held out: accepted (precision) | ceiling, held-out p_correct | ceiling, "
        "inliers | inliers of right / wrong answers (median) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in report["routes"].items():
        for which in ("test", "whole"):
            f = r[which]
            m = f["models"]
            inl = f["inliers"]
            med = "n/a" if inl["median_wrong"] is None else f"{inl['median_wrong']:g}"
            lines.append(
                f"| {name} | {which} ({f['n']}) | {f['right']:.3f} | {_model_cells(m)} | "
                f"{_pct(inl['ceiling'])} | {inl['median_right']:g} / {med} |"
            )
    return "\n".join(lines)


def sequence_table(report: dict[str, Any]) -> str:
    """Markdown: sequence mode, a row per route and part."""
    lines = [
        "| route | part | estimates right (recall@1) | shipped: accepted (precision) | "
        "ceiling, shipped p_correct | held out: accepted (precision) | ceiling, held-out "
        "p_correct |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in report["routes"].items():
        for which in ("test", "whole"):
            f = r[which]["sequence"]
            m = f["models"]
            lines.append(
                f"| {name} | {which} ({r[which]['n']}) | {f['right']:.3f} | {_model_cells(m)} |"
            )
    return "\n".join(lines)


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    add_json(
        ap, "--out", help="JSON record (default docs/experiments/acceptance/single_ceiling.json)"
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    sets = model_sets(args.config, list(ROUTES), args.foreign, args.nordland_frames)
    prov = provenance(args.config, sets.shipped_config, args)
    verifier = Verifier()
    report: dict[str, Any] = {
        "config": args.config,
        "target_precision": TARGET,
        "goal_single_share": 0.30,
        "verifier": Inliers().config.model_dump(),
        "routes": {},
    }
    for i, route in enumerate(sets.routes):
        policies = {"shipped": sets.shipped, "held_out": sets.folds[i][0]}
        report["routes"][route.name] = {
            which: part(route, which, policies, verifier, sets.params)
            for which in ("test", "whole")
        }
        print(f"{route.name} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["wall_s"] = time.perf_counter() - t0
    print(table(report))
    print()
    print(sequence_table(report))
    out = write_record(
        args.out or ROOT / "docs" / "experiments" / "acceptance" / "single_ceiling.json",
        report,
        prov=prov,
    )
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
