"""Sequence mode out of the box: what the filter finds and what the one policy accepts of it.

    python -m bench.sequence [--config default] [--foreign 200] [--nordland-frames 800]
        [--out docs/experiments/acceptance/sequence.json] [--plots DIR] [--tune]

The routes and their parts are ``bench/shipped_acceptance.py``'s (Gardens Point's three
protocols, Nordland summer -> winter, its first ``--nordland-frames`` frames; the preset on
all), split as ``hmpf-calibrate`` splits them (alternating stretches of 20 frames). The
filter is the preset's (its ``sequence:`` settings, the off-map state reading the test
part's own reference profile, as ``hmpf-eval --sequence`` and the service run it).

**What is accepted** is decided as the service decides it: :class:`hmpf.acceptance.Policy`
through :func:`hmpf.evaluation.acceptance.decide` / ``apply_acceptance`` (rule ``p_correct``
with the hysteresis, or ``lock``; the filter's off-map state refuses). Three policies:

* ``shipped``: the preset as a new user gets it (``load_config(preset)``: its shipped
  models; no ``hmpf-calibrate`` step), fitted on the training parts of these very routes:
  the test parts are new frames, not new places;
* ``held_out``: leave one route out, the models fitted by ``bench/shipped_acceptance.py``'s
  own procedure (:func:`shipped_acceptance.held_out`) on the *other* routes' training parts;
* ``no_model``: the quality / lock rules (what a preset without a model decides).

Per route, on the test part driven once, in order, as one vehicle (every frame counts):
sequence recall@1 (beside single frame; the policy does not change it), the share accepted
and its precision (the goal at precision >= 99 %: >= 85 % on every Gardens Point
protocol, >= 50 % on Nordland), lock flips per 100 frames (after the first acceptance, over
the drive; and inside the drive's *right, continuous* stretches, :func:`right_runs`: where
an estimate that stays right should stay accepted; goal <= 2), the share of in-map frames the
filter says are off the map, and ``--foreign`` frames of another data set driven in order
(share said off the map, share accepted) and a drive that leaves and comes back
(:func:`shipped_acceptance.evaluate`). The drives a fleet makes (40 random starts of 20
frames, 100 spliced jumps): frames to the first *accepted* answer under each policy.

The filter's own figures, which no policy changes (:func:`sequence_report`): frames until
the estimate is right for 5 frames after a start and after a jump, recall@1 by speed ratio
(0.5-4) and with 25 % of the frames dropped, recall by frames of history (plot).

**The whole traverses** (Gardens Point's three protocols, 200 frames each, the whole map):
sequence recall@1 as ``hmpf-eval --sequence`` measures it (the goal: >= 0.95 on
day_left -> night_right), with each policy's accepted share. A whole traverse includes the
training parts the shipped models (and the other folds' models) were fitted on: its
acceptance is not a held-out figure; its recall does not depend on the models.

``--tune`` (training parts only): a small grid of the filter's settings scored by the mean
sequence recall@1 of the four training parts' traverses (with the off-map state, as run);
the best setting is then compared with the preset's, paired frame by frame (sign test), on
the test parts (held out) and the whole traverses (which hold the training parts' frames:
not held out). It reports, it changes no default.

Every figure names the preset and its config digest, the machine, date and git commit
(:func:`shipped_acceptance.provenance`).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.shipped_acceptance import (
    ROUTES,
    TARGET,
    Route,
    add_route_arguments,
    evaluate,
    flips,
    held_out_fit,
    model_sets,
    out_of_the_box,
    report_head,
    route_policies,
)
from hmpf.acceptance import Policy
from hmpf.config import HierarchyConfig
from hmpf.datasets import GARDENS_POINT_PROTOCOLS
from hmpf.evaluation.acceptance import Answers, apply_acceptance, sequence_answers
from hmpf.evaluation.calibrate import paired_test
from hmpf.evaluation.sequence import (
    Drive,
    jump_drives,
    sequence_report,
    start_drives,
)
from hmpf.sequence import FilterParams, RouteMap

__all__ = [
    "first_accepts",
    "policy_figures",
    "pyplot",
    "right_runs",
    "run_flips",
]

#: The acceptance goals (bundled default preset, test parts / held-out folds).
GOAL_WHOLE = 0.95
GOAL_FLIPS = 2.0
GOAL_SEQUENCE = {"gp": 0.85, "nordland": 0.50}
#: A right, continuous stretch counts for the lock's flips from this many frames.
MIN_RUN = 10
POLICIES = ("shipped", "held_out", "no_model")
#: ``--tune``'s grid (over the preset's settings), scored on the training parts only.
TUNE_GRID: dict[str, tuple[Any, ...]] = {
    "evidence_weight": (0.1, 0.25, 0.5),
    "combined_weight": (1.0, 2.0, 4.0),
    "jump": (0.01, 0.02, 0.05),
    "jitter": (0.2, 0.35),
}


# -- pure helpers -------------------------------------------------------------------------------


def right_runs(answers: Answers, min_len: int = MIN_RUN) -> list[tuple[int, int]]:
    """``(start, end)`` of every stretch of at least ``min_len`` answers of one drive in
    which the estimate is right on every frame and continuous from its second frame on
    (the drive's *right, continuous* stretches: an estimate that stays right)."""
    assert answers.estimates is not None and answers.drive is not None
    out: list[tuple[int, int]] = []
    start: int | None = None
    n = len(answers)
    for i in range(n + 1):
        ok = i < n and bool(answers.correct[i])
        if ok and start is not None:
            same = answers.drive[i] == answers.drive[i - 1]
            ok = bool(same and answers.estimates[i].continuous)
            if not ok:  # this frame starts a new stretch if it is right
                if i - start >= min_len:
                    out.append((start, i))
                start = i
                continue
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            if i - start >= min_len:
                out.append((start, i))
            start = None
    return out


def run_flips(accepted: np.ndarray, runs: Sequence[tuple[int, int]]) -> tuple[int, int]:
    """(flips, frames) inside ``runs``: changes of ``accepted`` from one frame to the next
    within each stretch, and the stretches' frames."""
    a = np.asarray(accepted, dtype=bool)
    k = sum(int(np.sum(a[s + 1 : e] != a[s : e - 1])) for s, e in runs)
    return k, sum(e - s for s, e in runs)


def policy_figures(policy: Policy, answers: Answers, goal: float | None = None) -> dict[str, Any]:
    """The policy on one drive's sequence answers (:func:`apply_acceptance`, the service's
    decisions): recall@1, accepted share and precision (and whether they meet ``goal`` at
    precision >= 99 %), flips per 100 frames over the drive (after the first acceptance)
    and inside its right, continuous stretches, the share said off the map."""
    rep = apply_acceptance(policy, answers, sequence=True)
    acc = np.array(rep["accepted_answers"], bool)
    off = np.array(rep["off_map"], bool)
    runs = right_runs(answers)
    k, frames = run_flips(acc, runs)
    right = answers.correct
    out: dict[str, Any] = {
        "rule": rep["rule"],
        "n": len(answers),
        "recall_at_1": float(right.mean()) if len(answers) else 0.0,
        "accepted": rep["accepted"],
        "n_accepted": rep["n_accepted"],
        "precision": rep["precision"],
        "flips_per_100": 100.0 * flips(acc) / max(1, len(acc)),
        "right_runs": {
            "runs": len(runs),
            "frames": frames,
            "flips": k,
            "flips_per_100": 100.0 * k / frames if frames else None,
            "accepted": float(acc[np.concatenate([np.arange(s, e) for s, e in runs])].mean())
            if runs
            else None,
        },
        "said_off_map": float(off.mean()) if len(off) else 0.0,
        "right_said_off_map": float(off[right].mean()) if right.any() else None,
    }
    if goal is not None:
        p = rep["precision"]
        out["goal"] = goal
        out["goal_met"] = p is not None and p >= TARGET and rep["accepted"] >= goal
    fl = out["right_runs"]["flips_per_100"]
    out["flips_goal_met"] = None if fl is None else fl <= GOAL_FLIPS
    return out


def first_accepts(policy: Policy, answers: Answers, drives: Sequence[Drive]) -> dict[str, Any]:
    """Per drive of ``answers`` (:func:`sequence_answers` of ``drives``), the frames from the
    drive's start (or its splice) to its first accepted answer (1: that frame itself):
    median, 95th percentile, and the drives that never got one."""
    rep = apply_acceptance(policy, answers, sequence=True)
    acc = np.array(rep["accepted_answers"], bool)
    assert answers.drive is not None
    values: list[int | None] = []
    for i, d in enumerate(drives):
        a = acc[answers.drive == i][d.splice or 0 :]
        hit = np.flatnonzero(a)
        values.append(int(hit[0]) + 1 if len(hit) else None)
    got = np.array([v for v in values if v is not None], dtype=np.float64)
    return {
        "drives": len(drives),
        "median": float(np.median(got)) if len(got) else None,
        "p95": float(np.percentile(got, 95)) if len(got) else None,
        "never": int(sum(v is None for v in values)),
    }


def _f(x: float | None, fmt: str = ".3f") -> str:
    return "n/a" if x is None else format(x, fmt)


def _yes(x: bool | None) -> str:
    return "" if x is None else ("yes" if x else "no")


# -- one route's test part ----------------------------------------------------------------------


def fleet_drives(nq: int, seed: int = 0) -> tuple[list[Drive], list[Drive]]:
    """40 random starts of 20 frames and 100 spliced jumps (as :func:`sequence_report`)."""
    rng = np.random.default_rng(seed)
    starts = start_drives(nq, 40, 20, 1.0, rng)
    before, after = min(20, nq // 4), min(30, nq // 3)
    return starts, jump_drives(nq, 100, before, after, max(10, nq // 5), rng)


def filter_figures(rep: dict[str, Any]) -> dict[str, Any]:
    """:func:`sequence_report` without what the policy decides (its ``accepted`` is the bare
    ``lock_mass`` rule, not the service's) and without per-frame lists."""
    return {k: v for k, v in rep.items() if k not in ("accepted", "full_drive", "params")}


def route_figures(
    route: Route,
    config: HierarchyConfig,
    params: FilterParams,
    policies: dict[str, tuple[Policy, str]],
    digest: str,
) -> dict[str, Any]:
    """Every figure of one route's test part (see the module docstring)."""
    bank = route.test
    nq = route.n_test
    routes = RouteMap.from_metadata(bank.n_db)
    results = bank.results(config)[:nq]
    gt = np.asarray(bank.gt[:nq], bool)
    profile = bank.profile(config)
    gp = route.name.startswith("gp_")
    rep = sequence_report(results, gt, routes, params, profile=profile)
    seq = sequence_answers(results, gt, routes, params, None, profile)
    assert abs(float(seq.correct.mean()) - rep["recall_at_1"]) < 1e-12
    starts, jumps = fleet_drives(nq)
    s_ans = sequence_answers(results, gt, routes, params, starts, profile)
    j_ans = sequence_answers(results, gt, routes, params, jumps, profile)
    out: dict[str, Any] = {
        "n_test": nq,
        "n_reference": bank.n_db,
        "single_recall_at_1": rep["single_recall_at_1"],
        "recall_at_1": rep["recall_at_1"],
        "filter": filter_figures(rep),
    }
    goal = GOAL_SEQUENCE["gp" if gp else "nordland"]
    for key, (policy, models) in policies.items():
        ev = evaluate(route, policy, params)
        fig = policy_figures(policy, seq, goal)
        # The same decisions as bench/shipped_acceptance.py's own figures.
        assert abs(fig["accepted"] - ev["sequence"]["accepted"]) < 1e-12
        out[key] = {
            "preset": config.name,
            "digest": digest,
            "models": models,
            "sequence": fig,
            "single": ev["single"],
            "foreign": ev["foreign"],
            "leave_and_return": ev["leave_and_return"],
            "first_accept_after_start": first_accepts(policy, s_ans, starts),
            "first_accept_after_jump": first_accepts(policy, j_ans, jumps),
        }
    return out


# -- the whole traverses ------------------------------------------------------------------------


class Whole:
    """A Gardens Point protocol's whole traverse against its whole map (``hmpf-eval``): the
    route's own (:meth:`~bench.shipped_acceptance.Route.whole_results`, with its prior)."""

    def __init__(self, route: Route) -> None:
        bank = route.whole()
        self.name = route.name
        self.results, self.profile = route.whole_results()
        self.gt = np.asarray(bank.gt, bool)
        self.routes = RouteMap.from_metadata(bank.n_db)

    def answers(self, params: FilterParams) -> Answers:
        return sequence_answers(self.results, self.gt, self.routes, params, None, self.profile)


def whole_figures(
    whole: Whole,
    params: FilterParams,
    policies: dict[str, tuple[Policy, str]],
    config: HierarchyConfig,
    digest: str,
) -> dict[str, Any]:
    rep = sequence_report(whole.results, whole.gt, whole.routes, params, profile=whole.profile)
    seq = whole.answers(params)
    assert abs(float(seq.correct.mean()) - rep["recall_at_1"]) < 1e-12
    out: dict[str, Any] = {
        "n_query": len(whole.results),
        "single_recall_at_1": rep["single_recall_at_1"],
        "recall_at_1": rep["recall_at_1"],
        "vs_single": rep["vs_single"],
        "goal": GOAL_WHOLE if whole.name == "gp_dl_nr" else None,
        "goal_met": rep["recall_at_1"] >= GOAL_WHOLE if whole.name == "gp_dl_nr" else None,
        "wrong_frames": np.flatnonzero(~seq.correct).tolist(),
        "filter": filter_figures(rep),
    }
    for key, (policy, models) in policies.items():
        out[key] = {
            "preset": config.name,
            "digest": digest,
            "models": models,
            "sequence": policy_figures(policy, seq),
        }
    return out


# -- --tune: the filter's settings on the training parts only -----------------------------------


def tune(
    routes: Sequence[Route],
    wholes: Sequence[Whole],
    config: HierarchyConfig,
    base: FilterParams,
) -> dict[str, Any]:
    """``TUNE_GRID`` over ``base`` scored by the mean recall@1 of the training parts'
    traverses (each driven once, in order, with the off-map state); the best against
    ``base`` paired on the test parts and the whole traverses."""
    train = []
    for r in routes:
        bank = r.train.rows(np.arange(r.n_train))
        train.append(
            (
                bank.results(config),
                np.asarray(bank.gt, bool),
                RouteMap.from_metadata(bank.n_db),
                bank.profile(config),
            )
        )
    rows = []
    for values in itertools.product(*TUNE_GRID.values()):
        setting = dict(zip(TUNE_GRID, values, strict=True))
        params = base.with_(**setting)
        rec = [
            float(sequence_answers(res, gt, rm, params, None, prof).correct.mean())
            for res, gt, rm, prof in train
        ]
        rows.append({**setting, "recall": rec, "score": float(np.mean(rec))})
        print(f"tune {setting}: {np.round(rec, 3).tolist()} -> {rows[-1]['score']:.4f}", flush=True)
    base_setting = {k: getattr(base, k) for k in TUNE_GRID}
    best = max(  # ties: the preset's setting
        rows, key=lambda r: (r["score"], all(r[k] == base_setting[k] for k in TUNE_GRID))
    )
    chosen = base.with_(**{k: best[k] for k in TUNE_GRID})
    base_row = next(r for r in rows if all(r[k] == base_setting[k] for k in TUNE_GRID))

    def paired(results: Any, gt: Any, rm: RouteMap, prof: Any) -> dict[str, Any]:
        a = sequence_answers(results, gt, rm, chosen, None, prof).correct
        b = sequence_answers(results, gt, rm, base, None, prof).correct
        return {"tuned": float(a.mean()), "preset": float(b.mean()), **paired_test(a, b)}

    test = {}
    for r in routes:
        nq = r.n_test
        res = r.test.results(config)[:nq]
        test[r.name] = paired(
            res,
            np.asarray(r.test.gt[:nq], bool),
            RouteMap.from_metadata(r.test.n_db),
            r.test.profile(config),
        )
    whole = {w.name: paired(w.results, w.gt, w.routes, w.profile) for w in wholes}
    return {
        "grid": {k: list(v) for k, v in TUNE_GRID.items()},
        "rows": rows,
        "preset_setting": {**base_setting, "score": base_row["score"]},
        "chosen": {k: best[k] for k in TUNE_GRID},
        "chosen_score": best["score"],
        "test_parts": test,
        "whole_traverses": whole,
    }


# -- output -------------------------------------------------------------------------------------


def pyplot() -> Any:
    """matplotlib's pyplot on the file backend, or None (said) when it is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib missing (pip install 'hmpf[report]'): no plots")
        return None
    return plt


def plot(report: dict[str, Any], path: Path) -> Path | None:
    """Recall@1 by frames of history, one line per speed ratio, one panel per route."""
    plt = pyplot()
    if plt is None:
        return None
    reps = {
        name: r["filter"] | {"single": r["single_recall_at_1"]}
        for name, r in report["routes"].items()
    }
    fig, axes = plt.subplots(1, len(reps), figsize=(4.2 * len(reps), 3.6), sharey=True)
    for ax, (name, rep) in zip(np.atleast_1d(axes), reps.items(), strict=True):
        for ratio, curve in rep["recall_by_history"].items():
            if curve:
                ax.plot(np.arange(1, len(curve) + 1), curve, marker=".", label=f"x{ratio}")
        ax.axhline(rep["single"], color="grey", ls="--", label="single frame")
        ax.set_title(name)
        ax.set_xlabel("frames since the start of the drive")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("recall@1 (test part)")
    np.atleast_1d(axes)[-1].legend(title="speed ratio", fontsize=8)
    fig.suptitle(
        f"preset {report['preset']!r} ({report['digest'][:12]}), commit "
        f"{(report['commit'] or '?')[:7]}",
        fontsize=9,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def table(report: dict[str, Any]) -> str:
    """Markdown table: per route's test part and policy, the sequence-mode figures."""
    lines = [
        "| route (test part) | models | rule | seq. recall@1 (single) | accepted (precision) "
        "| goal met | flips / 100: drive, right stretches (frames) | said off map: in map, "
        "foreign | foreign accepted | first accept after start / jump (median, p95, never) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in report["routes"].items():
        for key in POLICIES:
            e = r[key]
            q, rr, f = e["sequence"], e["sequence"]["right_runs"], e["foreign"]
            s, j = e["first_accept_after_start"], e["first_accept_after_jump"]
            lines.append(
                f"| {name} ({q['n']}) | {key.replace('_', ' ')} | {q['rule']} | "
                f"{q['recall_at_1']:.3f} ({r['single_recall_at_1']:.3f}) | "
                f"{q['accepted']:.3f} ({_f(q['precision'])}) | {_yes(q.get('goal_met'))} | "
                f"{q['flips_per_100']:.1f}, {_f(rr['flips_per_100'], '.1f')} ({rr['frames']}) | "
                f"{q['said_off_map']:.3f}, {f['sequence_off_map']:.3f} | "
                f"{f['sequence_accepted']:.3f} | "
                f"{_f(s['median'], '.0f')}, {_f(s['p95'], '.0f')}, {s['never']} / "
                f"{_f(j['median'], '.0f')}, {_f(j['p95'], '.0f')}, {j['never']} |"
            )
    return "\n".join(lines)


def filter_table(report: dict[str, Any]) -> str:
    """Markdown table: the filter's own figures (no policy changes them)."""
    lines = [
        "| route (test part) | single frame | sequence | right for 5 frames after start "
        "(median / p95) | after jump: within 10 (p95) | x0.5 / x2 / x4 | 25 % dropped |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in report["routes"].items():
        f = r["filter"]
        ls, lj, sp = f["lock_after_start"], f["lock_after_jump"], f["recall_by_speed"]
        lines.append(
            f"| {name} ({r['n_test']}) | {r['single_recall_at_1']:.3f} | "
            f"**{r['recall_at_1']:.3f}** | {ls['median']:.0f} / {ls['p95']:.0f} | "
            f"{lj['within_10']:.2f} ({lj['p95']:.0f}) | {sp['0.5']:.3f} / {sp['2']:.3f} / "
            f"{sp['4']:.3f} | {f['dropped']['recall_at_1']:.3f} |"
        )
    return "\n".join(lines)


def whole_table(report: dict[str, Any]) -> str:
    """Markdown table: the whole traverses."""
    lines = [
        "| whole traverse | frames | single frame | sequence recall@1 | vs single (wins / "
        "losses, p) | goal >= 0.95 | accepted (precision): shipped / held out / no model "
        "| flips / 100 right stretches: shipped / held out / no model |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, w in report["whole"].items():
        v = w["vs_single"]
        acc = " / ".join(
            f"{w[k]['sequence']['accepted']:.3f} ({_f(w[k]['sequence']['precision'])})"
            for k in POLICIES
        )
        fl = " / ".join(
            _f(w[k]["sequence"]["right_runs"]["flips_per_100"], ".1f") for k in POLICIES
        )
        lines.append(
            f"| {name} | {w['n_query']} | {w['single_recall_at_1']:.3f} | "
            f"**{w['recall_at_1']:.3f}** | {v['wins']} / {v['losses']}, {v['p']:.2g} | "
            f"{_yes(w['goal_met'])} | {acc} | {fl} |"
        )
    return "\n".join(lines)


def tune_table(t: dict[str, Any]) -> str:
    lines = [
        f"chosen on the training parts: {t['chosen']} (score {t['chosen_score']:.4f}; the "
        f"preset's {t['preset_setting']['score']:.4f})",
        "",
        "| held-out frames | tuned recall@1 | preset recall@1 | wins / losses | p |",
        "|---|---|---|---|---|",
    ]
    groups = {"test_parts": "test part", "whole_traverses": "whole, holds the training part"}
    for group, what in groups.items():
        for name, r in t[group].items():
            lines.append(
                f"| {name} ({what}) | {r['tuned']:.3f} | {r['preset']:.3f} | "
                f"{r['wins']} / {r['losses']} | {r['p']:.2g} |"
            )
    return "\n".join(lines)


# -- the run ------------------------------------------------------------------------------------


NOTE = (
    "2 shared CPU cores (other jobs running): the figures do not depend on it, "
    "wall_s does. 100 test queries per Gardens Point protocol (200 per whole "
    "traverse): one frame moves a recall by 1 (0.5) point; close rivals cannot be "
    "told apart."
)


def print_report(report: dict[str, Any], digest: str, out: Path) -> None:
    print(
        f"preset {report['preset']!r} (digest {digest[:12]}), "
        f"commit {(report['commit'] or '?')[:7]}, {report['machine']}, {report['date']}"
    )
    print(table(report))
    print()
    print(filter_table(report))
    print()
    print(whole_table(report))
    if "tune" in report:
        print()
        print(tune_table(report["tune"]))
    print(f"wrote {out} ({report['wall_s']:.0f} s)")


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    ap.add_argument("--routes", default=",".join(ROUTES), help="comma-separated (>= 3)")
    ap.add_argument("--tune", action="store_true", help="also the training-part filter grid")
    add_json(ap, "--out", default=str(ROOT / "docs/experiments/acceptance/sequence.json"))
    ap.add_argument(
        "--plots", default=str(ROOT / "docs/experiments/acceptance/sequence_history_by_speed.png")
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    # the commit of the code loaded, not the end's
    prov = provenance(args.config, out_of_the_box(args.config)[1], args)
    names = args.routes.split(",")
    sets = model_sets(args.config, names, args.foreign, args.nordland_frames)
    config, params, routes = sets.config, sets.params, sets.routes
    digest = config.digest()
    by_route = {r.name: r for r in routes}
    wholes = [Whole(by_route[n]) for n in GARDENS_POINT_PROTOCOLS if n in by_route]
    print(f"whole traverses ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    goals = {
        "whole_gp_dl_nr_recall": GOAL_WHOLE,
        "sequence_accepted": GOAL_SEQUENCE,
        "flips_per_100": GOAL_FLIPS,
    }
    report: dict[str, Any] = {
        **prov,
        **report_head(args, sets, NOTE, goals, filter_key="filter_params"),
        "right_run_min_frames": MIN_RUN,
        "routes": {},
        "whole": {},
    }
    by_name = {}
    for i, route in enumerate(routes):
        by_name[route.name] = policies = route_policies(sets, i)
        report["routes"][route.name] = {
            **route_figures(route, config, params, policies, digest),
            "held_out_fit": held_out_fit(sets, i),
        }
        print(f"{route.name} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    for w in wholes:  # with the fold that held this protocol out
        report["whole"][w.name] = whole_figures(w, params, by_name[w.name], config, digest)
    print(f"whole traverses done ({time.perf_counter() - t0:.0f} s)", flush=True)
    figure = plot(report, Path(args.plots)) if args.plots else None
    report["figure"] = None if figure is None else str(figure)
    if args.tune:
        report["tune"] = tune(routes, wholes, config, params)
        print(f"tuning done ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["wall_s"] = time.perf_counter() - t0
    print_report(report, digest, write_record(args.out, report, prov=prov))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
