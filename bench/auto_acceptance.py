"""The acceptance ``--config auto`` gives a preset it keeps: shipped, or fitted on pseudo-queries?

    python -m bench.auto_acceptance [--config default] [--routes gp_dr_nr,...] [--foreign 200]
        [--nordland-frames 800] [--seed 0] [--out docs/experiments/auto_config/acceptance.json]

``hmpf-index build --config auto`` (:func:`hmpf.evaluation.auto.auto`) fits the chosen
hierarchy's acceptance on its pseudo-query answers
(:func:`hmpf.evaluation.calibrate.fit_config_acceptance` with ``model=True, outside=True``:
a z threshold and a *single-frame* confidence model; no sequence model, so sequence mode
falls back to the lock rule). A bundled preset ships models fitted on real queries of four
routes pooled (``bench/shipped_acceptance.py``, single frame *and* sequence). When auto keeps
the preset, which acceptance should its version carry? Three variants of the preset's
acceptance, all decided by the one policy (:class:`hmpf.acceptance.Policy` through
:func:`hmpf.evaluation.acceptance.apply_acceptance`):

* ``shipped`` (a): the preset as it ships (:func:`bench.shipped_acceptance.out_of_the_box`);
* ``pseudo`` (b): what auto fits today, on pseudo-queries of the route's *training part's
  references only* (no query, nothing of the test part): auto's own steps 1, 2 and 5
  (:func:`~hmpf.evaluation.pseudo.route_positions`, :func:`~hmpf.evaluation.pseudo.plan`,
  :func:`~hmpf.evaluation.auto.pseudo_bank` over :func:`~hmpf.evaluation.auto.auto_pool`,
  :func:`~hmpf.evaluation.calibrate.fit_config_acceptance`) with auto's defaults and each
  training stretch as its own ``sequence`` (as ``bench/auto_config.py`` gives them); the
  search and check (steps 3-4) are skipped: they choose the hierarchy, and the preset is
  given. Sequence mode: the lock rule;
* ``pseudo+seq`` (c): (b)'s single-frame model and z threshold with the shipped sequence
  model, its thresholds and stay threshold (:func:`combine`).

Routes and split are ``bench/shipped_acceptance.py``'s (:class:`~bench.shipped_acceptance.
Route`: Gardens Point's three protocols and Nordland summer -> winter, its first 800 frames;
alternating stretches of 20 frames, +-2 frames), so the shipped models never saw a test
frame. On each route's *test* part (:func:`bench.confidence.route_answers`,
:func:`bench.confidence.measure`): single frame and the test part driven once in sequence
mode: the share accepted, its precision, ECE of ``p_correct`` (with its sampling floor), lock
flips per 100 frames; ``--foreign`` frames of another data set against the map (Nordland
winter against the Gardens Point maps, Gardens Point night_right against Nordland's), single
frame and driven in order: the share accepted and the mean ``p_correct``. Per route and mode,
paired sign tests between the variants on the accepted-and-right flags (in the map) and the
accepted flags (foreign frames), and the same pooled over the routes.

Writes the JSON record (:func:`bench.harness.provenance`: preset, config digest, machine,
date, commit) and its Markdown printout beside it (``.md``).
"""

from __future__ import annotations

import inspect
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.auto_config import stretch_sequence
from bench.confidence import MODES, measure, pooled, route_answers, strip
from bench.harness import ROOT, add_json, parser, provenance, write_json
from bench.shipped_acceptance import (
    BLOCK,
    ROUTES,
    Route,
    add_route_arguments,
    limit_of,
    out_of_the_box,
)
from hmpf.acceptance import Policy
from hmpf.config import HierarchyConfig
from hmpf.evaluation.acceptance import apply_acceptance
from hmpf.evaluation.auto import auto, auto_pool, pseudo_bank
from hmpf.evaluation.calibrate import fit_config_acceptance
from hmpf.evaluation.metrics import paired_test
from hmpf.evaluation.pseudo import plan, route_positions
from hmpf.features import FeatureCache
from hmpf.runtime import default_cache_dir

#: The variants, in the order reported: (a), (b), (c) of the module docstring.
VARIANTS = ("shipped", "pseudo", "pseudo+seq")
#: The pairs compared by sign tests.
PAIRS = (("shipped", "pseudo"), ("shipped", "pseudo+seq"), ("pseudo+seq", "pseudo"))
#: Auto's own defaults (:func:`hmpf.evaluation.auto.auto`), read from its signature so the
#: fit here is the one an index build runs.
AUTO_DEFAULTS = {k: p.default for k, p in inspect.signature(auto).parameters.items()}
GOALS = {
    "precision": 0.99,
    "foreign_accepted_max": 0.01,
    "foreign_mean_p_max": 0.1,
    "flips_per_100_max": 2.0,
    "sequence_ece_pooled_max": 0.05,
}
DEFAULT_OUT = ROOT / "docs" / "experiments" / "auto_config" / "acceptance.json"


def combine(single: Policy, sequence: Policy) -> Policy:
    """``single``'s single-frame rules (z threshold, model and its threshold) with
    ``sequence``'s sequence-mode rules (sequence model, its thresholds, the lock rule's
    masses)."""
    return replace(
        single,
        sequence_model=sequence.sequence_model,
        sequence_threshold=sequence.sequence_threshold,
        sequence_stay_threshold=sequence.sequence_stay_threshold,
        lock_mass=sequence.lock_mass,
        unlock_mass=sequence.unlock_mass,
    )


def pseudo_acceptance(
    config: HierarchyConfig,
    references: Sequence[str | Path],
    metadata: Mapping[str, Any] | None,
    cache: FeatureCache | None,
    *,
    seed: int = 0,
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """``config`` with the acceptance auto fits when it keeps it: its steps 1, 2 and 5 on
    ``references`` (auto's defaults); with the pseudo-query training figures."""
    a = AUTO_DEFAULTS
    t0 = time.perf_counter()
    where = route_positions(len(references), metadata)
    plan_ = plan(
        where,
        seed=seed,
        max_references=a["max_references"],
        max_queries=a["max_queries"],
        tolerance=a["tolerance"],
        radius_m=a["radius_m"],
    )
    with tempfile.TemporaryDirectory(prefix="hmpf-auto-acceptance-") as tmp:
        bank, times = pseudo_bank(auto_pool(), references, plan_, tmp, cache=cache)
    t1 = time.perf_counter()
    fit = fit_config_acceptance(
        config.model_copy(update={"acceptance": None}),
        bank,
        target_precision=a["target_precision"],
        seed=seed,
        model=a["model"],
        outside=a["outside"],
    )
    times["acceptance_s"] = time.perf_counter() - t1
    times["total_s"] = time.perf_counter() - t0
    conf = fit.confidence or {}
    record = {
        "sample": plan_.summary(),
        "z": fit.acceptance,
        "confidence": {
            mode: {k: v for k, v in figs.items() if not isinstance(v, list) or len(v) < 50}
            for mode, figs in conf.items()
        },
        "time_s": times,
    }
    return fit.config, record


def flags(policy: Policy, answers: Any, sequence: bool) -> np.ndarray:
    """Per answer: accepted by ``policy`` (the one policy, :func:`apply_acceptance`)."""
    return np.array(apply_acceptance(policy, answers, sequence=sequence)["accepted_answers"], bool)


def sign_tests(per_variant: Mapping[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """Paired sign tests of :data:`PAIRS` on ``per_variant``'s flags (same answers)."""
    return {
        f"{a} vs {b}": paired_test(per_variant[a], per_variant[b])
        for a, b in PAIRS
        if a in per_variant and b in per_variant
    }


def route_flags(
    policies: Mapping[str, Policy], answers: Mapping[str, Any]
) -> dict[str, dict[str, np.ndarray]]:
    """Per mode, per variant: accepted-and-right in the map (``single``, ``sequence``),
    accepted-and-wrong in the map (``single_wrong``, ``sequence_wrong``) and accepted for the
    foreign frames (``foreign_single``, ``foreign_sequence``)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for mode in MODES:
        seq = mode == "sequence"
        inside = {v: flags(p, answers[mode], seq) for v, p in policies.items()}
        right = answers[mode].correct
        out[mode] = {v: x & right for v, x in inside.items()}
        out[f"{mode}_wrong"] = {v: x & ~right for v, x in inside.items()}
        far = answers[f"foreign_{mode}"]
        out[f"foreign_{mode}"] = {v: flags(p, far, seq) for v, p in policies.items()}
    return out


def pooled_counts(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Accepted share and precision of ``rows`` (each ``n``, ``accepted``, ``precision``)
    pooled by counts."""
    n = sum(int(r["n"]) for r in rows)
    acc = sum(round(r["accepted"] * r["n"]) for r in rows)
    right = sum(round((r["precision"] or 0.0) * round(r["accepted"] * r["n"])) for r in rows)
    return {"n": n, "accepted": acc / n if n else 0.0, "precision": right / acc if acc else None}


def single_figures(row: Mapping[str, Any]) -> dict[str, Any]:
    """A :func:`bench.confidence.measure` single-frame row's headline figures."""
    cal = row["calibration"]
    return {
        "accepted": row["accepted"],
        "precision": row["precision"],
        "ece": cal.get("ece"),
        "mean_p": cal.get("mean_p"),
        "foreign_accepted": row["foreign"]["accepted"],
        "foreign_mean_p": row["foreign"]["mean_p"],
    }


# -- output -------------------------------------------------------------------------------------


def _f(x: float | None, fmt: str = ".3f") -> str:
    return "n/a" if x is None else format(x, fmt)


def table(report: Mapping[str, Any]) -> str:
    """Markdown: per route and variant, both modes in the map and off it."""
    lines = [
        "| route (test queries) | acceptance | single accepted (prec.) | single ECE (floor) | "
        "sequence rule | sequence accepted (prec.) | seq. ECE (floor) | flips / 100 | "
        "foreign single accepted / mean p | foreign seq. accepted / mean p |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def ece(cal: Mapping[str, Any]) -> str:
        if cal.get("ece") is None:
            return "n/a"
        return f"{cal['ece']:.3f} ({cal['sampling_floor']:.3f})"

    for name, entry in report["routes"].items():
        for v in VARIANTS:
            s, q = entry[v]["single"], entry[v]["sequence"]
            lines.append(
                f"| {name} ({s['n']}) | {v} | {s['accepted']:.3f} ({_f(s['precision'])}) | "
                f"{ece(s['calibration'])} | {q['rule']} | {q['accepted']:.3f} "
                f"({_f(q['precision'])}) | {ece(q['calibration'])} | "
                f"{q['flips_per_100']:.1f} | {s['foreign']['accepted']:.3f} / "
                f"{_f(s['foreign']['mean_p'])} | {q['foreign']['accepted']:.3f} / "
                f"{_f(q['foreign']['mean_p'])} |"
            )
    return "\n".join(lines)


def tests_table(report: Mapping[str, Any]) -> str:
    """Markdown: the sign tests (wins / losses, p) per route and pooled."""
    keys = [f"{a} vs {b}" for a, b in PAIRS]
    lines = [
        "| route | flags | " + " | ".join(keys) + " |",
        "|---|---|" + "---|" * len(keys),
    ]
    what = {
        "single": "single: accepted and right",
        "single_wrong": "single: accepted and wrong",
        "sequence": "sequence: accepted and right",
        "sequence_wrong": "sequence: accepted and wrong",
        "foreign_single": "foreign single: accepted",
        "foreign_sequence": "foreign sequence: accepted",
    }
    rows = {**{n: e["sign_tests"] for n, e in report["routes"].items()}}
    rows["pooled"] = report["pooled"]["sign_tests"]
    for name, tests in rows.items():
        for kind, label in what.items():
            t = tests[kind]
            cells = [f"{t[k]['wins']} / {t[k]['losses']}, p = {t[k]['p']:.2g}" for k in keys]
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def pooled_table(report: Mapping[str, Any]) -> str:
    """Markdown: per variant, the routes pooled (counts) and the pooled ECE."""
    lines = [
        "| acceptance | routes | single accepted (prec.) | single ECE | sequence accepted (prec.) "
        "| sequence ECE |",
        "|---|---|---|---|---|---|",
    ]
    for v in VARIANTS:
        pv = report["pooled"][v]
        for group in ("all", "gardens_point"):
            s, q = pv["counts"][group]["single"], pv["counts"][group]["sequence"]
            es = pv["ece"]["single"][group]["ece"]
            eq = pv["ece"]["sequence"][group]["ece"]
            lines.append(
                f"| {v} | {group} | {s['accepted']:.3f} ({_f(s['precision'])}) | {_f(es)} | "
                f"{q['accepted']:.3f} ({_f(q['precision'])}) | {_f(eq)} |"
            )
    return "\n".join(lines)


def seeds_table(report: Mapping[str, Any]) -> str:
    """Markdown: (b)'s single-frame figures for every seed of the pseudo-queries."""
    lines = [
        "| route | seed | threshold | single accepted (prec.) | single ECE | "
        "foreign single accepted / mean p |",
        "|---|---|---|---|---|---|",
    ]
    for name, entry in report["routes"].items():
        first = entry["pseudo"]
        rows = {
            str(report["arguments"]["seed"]): {
                "single_threshold": first["policy"]["model"]["threshold"]
                if first["policy"]["model"]
                else None,
                "single": single_figures(first["single"]),
            },
            **entry.get("pseudo_other_seeds", {}),
        }
        for seed, r in rows.items():
            s = r["single"]
            lines.append(
                f"| {name} | {seed} | {_f(r['single_threshold'])} | {s['accepted']:.3f} "
                f"({_f(s['precision'])}) | {_f(s['ece'])} | {s['foreign_accepted']:.3f} / "
                f"{_f(s['foreign_mean_p'])} |"
            )
    return "\n".join(lines)


def markdown(report: Mapping[str, Any]) -> str:
    head = (
        f"Preset `{report['preset']}` (config digest `{report['digest'][:12]}`), "
        f"{report['machine']}, {report['date']}, commit {str(report.get('commit'))[:10]}. "
        f"Test parts, +-2 frames; {report['foreign_frames']} foreign frames per map; Nordland's "
        f"first {report['nordland_frames']} frames."
    )
    return "\n\n".join(
        [
            head,
            table(report),
            "Routes pooled:",
            pooled_table(report),
            "Paired sign tests (wins / losses of the first against the second, two-sided p):",
            tests_table(report),
            "(b) on other draws of pseudo-queries (auto's seed), single frame:",
            seeds_table(report),
        ]
    )


NOTE = (
    "2 shared CPU cores (other jobs running): the figures do not depend on it, time_s does. "
    "About 100 test queries per Gardens Point protocol (400 on Nordland's first 800 frames): "
    "one answer moves a precision of 99 % by about one point; differences between variants "
    "are judged by the paired sign tests."
)


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    ap.add_argument("--routes", default=",".join(ROUTES), help="comma-separated")
    ap.add_argument("--seed", type=int, default=0, help="auto's seed (the pseudo-queries)")
    ap.add_argument(
        "--other-seeds",
        default="1,2",
        help="comma-separated seeds whose pseudo fits' single-frame figures are reported too "
        "(how much (b) depends on the draw of pseudo-queries); empty: none",
    )
    add_json(ap, "--out", default=str(DEFAULT_OUT))
    args = ap.parse_args()
    t0 = time.perf_counter()
    shipped_config, config, shipped = out_of_the_box(args.config)
    params = shipped_config.sequence_params()
    digest = config.digest()
    prov = provenance(args.config, config, args)
    cache = FeatureCache(default_cache_dir())
    report: dict[str, Any] = {
        **prov,
        "note": NOTE,
        "goals": GOALS,
        "variants": {
            "shipped": "(a) the preset's shipped acceptance (hmpf/presets/acceptance)",
            "pseudo": "(b) auto's fit on pseudo-queries of the training part's references "
            "(single-frame model; sequence: lock rule)",
            "pseudo+seq": "(c) (b)'s single-frame model with the shipped sequence model",
        },
        "split_block": BLOCK,
        "foreign_frames": args.foreign,
        "nordland_frames": args.nordland_frames or "all",
        "auto_defaults": {
            k: AUTO_DEFAULTS[k]
            for k in ("max_references", "max_queries", "tolerance", "radius_m", "target_precision")
        },
        "routes": {},
    }
    answers: dict[str, dict[str, Any]] = {}
    runs: dict[str, dict[str, Any]] = {v: {} for v in VARIANTS}
    all_flags: dict[str, dict[str, list[np.ndarray]]] = {}
    for name in args.routes.split(","):
        route = Route(name, config, cache, args.foreign, limit_of(name, args.nordland_frames))
        print(f"[{name}] banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
        refs = route.train_data.reference
        meta = {"sequence": stretch_sequence(len(refs), BLOCK)}
        fitted, fit_record = pseudo_acceptance(config, refs, meta, cache, seed=args.seed)
        pseudo = Policy.of(fitted.acceptance, lock_mass=params.lock_mass)
        print(f"[{name}] pseudo fit ({time.perf_counter() - t0:.0f} s)", flush=True)
        policies = {"shipped": shipped, "pseudo": pseudo, "pseudo+seq": combine(pseudo, shipped)}
        answers[name] = route_answers(route, config, params)
        gp = name.startswith("gp_")
        entry: dict[str, Any] = {
            "n_train_references": len(refs),
            "n_test": route.n_test,
            "n_foreign": route.n_foreign,
            "pseudo_fit": fit_record,
        }
        for v, policy in policies.items():
            entry[v] = {
                "preset": args.config,
                "digest": digest,
                "policy": policy.describe(),
                **measure(policy, answers[name], gp),
            }
            runs[v][name] = entry[v]
        entry["pseudo_other_seeds"] = {}
        for seed in [int(x) for x in args.other_seeds.split(",") if x.strip()]:
            other, rec = pseudo_acceptance(config, refs, meta, cache, seed=seed)
            pol = Policy.of(other.acceptance, lock_mass=params.lock_mass)
            entry["pseudo_other_seeds"][str(seed)] = {
                "single_threshold": pol.model_threshold,
                "single": single_figures(measure(pol, answers[name], gp)["single"]),
                "pseudo_fit": rec,
            }
            print(f"[{name}] pseudo fit, seed {seed} ({time.perf_counter() - t0:.0f} s)")
        fl = route_flags(policies, answers[name])
        entry["sign_tests"] = {k: sign_tests(per) for k, per in fl.items()}
        entry["flags"] = {
            "right_single": answers[name]["single"].correct.astype(int).tolist(),
            "right_sequence": answers[name]["sequence"].correct.astype(int).tolist(),
            **{f"{k}:{v}": x.astype(int).tolist() for k, per in fl.items() for v, x in per.items()},
        }
        for k, per in fl.items():
            for v, x in per.items():
                all_flags.setdefault(k, {}).setdefault(v, []).append(x)
        report["routes"][name] = entry
        print(f"[{name}] done ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["pooled"] = {
        "sign_tests": {
            k: sign_tests({v: np.concatenate(xs) for v, xs in per.items()})
            for k, per in all_flags.items()
        }
    }
    for v in VARIANTS:
        gp_names = [n for n in runs[v] if n.startswith("gp_")]
        groups = {"all": list(runs[v]), "gardens_point": gp_names}
        report["pooled"][v] = {
            "ece": pooled(runs[v], answers),
            "counts": {
                g: {m: pooled_counts([runs[v][n][m] for n in names]) for m in MODES}
                for g, names in groups.items()
            },
        }
    report["wall_s"] = time.perf_counter() - t0
    out = write_json(args.out, strip(report))
    text = markdown(report)
    Path(args.out).with_suffix(".md").write_text(text + "\n")
    print(text)
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
