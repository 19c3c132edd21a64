"""The acceptance ``--config auto`` gives a preset it keeps: shipped, or fitted on pseudo-queries?

    python -m bench.auto_acceptance [--config default] [--routes gp_dr_nr,...] [--foreign 200]
        [--nordland-frames 800] [--seed 0] [--out docs/experiments/auto_config/acceptance.json]
    python -m bench.auto_acceptance --found nordland_s_w=auto,nordland_s_w=thumbnails,\
        gp_dl_nr=netvlad-lite1,gp_dr_nr=netvlad-lite1 [--out .../acceptance_found.json]

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

**A hierarchy without shipped models** (``--found ROUTE=HIERARCHY,...``): a hierarchy the
search found (``auto``: the one :func:`hmpf.evaluation.auto.auto` chooses on the route's
training part as ``bench/auto_config.py`` runs it, read from ``auto_config.json`` when it
holds the route, else run here) or a bundled preset / YAML that ships no models. It serves
with the pseudo-query fit; which *sequence* acceptance? Three variants
(:data:`FOUND_VARIANTS`), the pseudo-query fit made on this bench's training part as above
(the pseudo bank over :func:`~hmpf.evaluation.auto.auto_pool` when the hierarchy runs on it,
else over the hierarchy's own methods):

* ``pseudo`` (b): auto's fit (single-frame model; sequence: the lock rule) -- what ships;
* ``pseudo-seq`` (d): ``fit_config_acceptance(..., sequence=True, model=True,
  outside=True)`` on the same pseudo bank: the filter's settings tuned and a sequence model
  fitted on drives over the pseudo-queries; sequence mode runs with the tuned settings;
* ``pseudo+default-seq`` (e): (b)'s single-frame model with the ``default`` preset's shipped
  sequence model, thresholds and stay threshold (:func:`combine`), on the hierarchy's own
  filter settings; whether its features are defined for the hierarchy is recorded
  (:func:`undefined_features`: the profile features need a tier-1 global method).

Same test parts, figures and sign tests; besides the pairs of variants, each variant against
the ``default`` preset's shipped acceptance on the same frames (its flags read from
``--baseline``, this bench's record for the default: what ``--config auto`` serves when it
keeps the default).

Writes the JSON record (:func:`bench.harness.provenance`: preset, config digest, machine,
date, commit; with ``--found`` every hierarchy's digest) and its Markdown printout beside it
(``.md``).
"""

from __future__ import annotations

import inspect
import json
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.auto_config import BLOCKS, route_parts, stretch_sequence
from bench.auto_config import DEFAULT_OUT as AUTO_CONFIG_OUT
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
from hmpf.confidence import ALL_FEATURES, PROFILE_FEATURES
from hmpf.config import ConfigError, HierarchyConfig, load_config, shipped_acceptance
from hmpf.datasets import dataset_root
from hmpf.evaluation.acceptance import apply_acceptance
from hmpf.evaluation.auto import auto, auto_pool, pseudo_bank
from hmpf.evaluation.calibrate import describe, fit_config_acceptance
from hmpf.evaluation.metrics import paired_test
from hmpf.evaluation.pseudo import plan, route_positions
from hmpf.evaluation.study import ScoreBank, check_compatible
from hmpf.features import FeatureCache
from hmpf.methods.base import GlobalMethod
from hmpf.methods.registry import get_method_class
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
#: ``--found``: the variants of a hierarchy without shipped models (module docstring).
FOUND_VARIANTS = ("pseudo", "pseudo-seq", "pseudo+default-seq")
FOUND_PAIRS = (
    ("pseudo-seq", "pseudo"),
    ("pseudo+default-seq", "pseudo"),
    ("pseudo+default-seq", "pseudo-seq"),
)
#: The reference every variant is compared with: the ``default`` preset's shipped
#: acceptance on the same frames (``--baseline``'s ``shipped`` flags).
BASELINE = "default shipped"
FOUND_OUT = ROOT / "docs" / "experiments" / "auto_config" / "acceptance_found.json"
#: The preset whose shipped sequence model (e) carries over.
CARRIED = "default"


def combine(single: Policy, sequence: Policy) -> Policy:
    """``single``'s single-frame rules (z threshold, model and its threshold) with
    ``sequence``'s sequence-mode rules (sequence model, its thresholds, the stay rule's
    evidence floor, the lock rule's masses)."""
    return replace(
        single,
        sequence_model=sequence.sequence_model,
        sequence_threshold=sequence.sequence_threshold,
        sequence_stay_threshold=sequence.sequence_stay_threshold,
        sequence_stay_ref_z=sequence.sequence_stay_ref_z,
        lock_mass=sequence.lock_mass,
        unlock_mass=sequence.unlock_mass,
    )


def pseudo_plan_bank(
    references: Sequence[str | Path],
    metadata: Mapping[str, Any] | None,
    cache: FeatureCache | None,
    *,
    seed: int = 0,
    pool: HierarchyConfig | None = None,
) -> tuple[Any, ScoreBank, dict[str, float]]:
    """Auto's steps 1 and 2 on ``references`` (auto's defaults): the plan of pseudo-queries
    and their score bank over ``pool`` (default :func:`auto_pool`), with the seconds each
    step took."""
    a = AUTO_DEFAULTS
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
        bank, times = pseudo_bank(pool or auto_pool(), references, plan_, tmp, cache=cache)
    return plan_, bank, times


def pseudo_fit(
    config: HierarchyConfig,
    bank: ScoreBank,
    *,
    seed: int = 0,
    sequence: bool = False,
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """Auto's step 5 on the pseudo bank (auto's defaults; with ``sequence`` the filter's
    settings and a sequence model too): ``config`` with that acceptance, and the training
    figures."""
    a = AUTO_DEFAULTS
    t0 = time.perf_counter()
    fit = fit_config_acceptance(
        config.model_copy(update={"acceptance": None}),
        bank,
        target_precision=a["target_precision"],
        seed=seed,
        sequence=sequence,
        model=a["model"],
        outside=a["outside"],
    )
    conf = fit.confidence or {}
    record: dict[str, Any] = {
        "z": fit.acceptance,
        "confidence": {
            mode: {k: v for k, v in figs.items() if not isinstance(v, list) or len(v) < 50}
            for mode, figs in conf.items()
        },
        "acceptance_s": time.perf_counter() - t0,
    }
    if sequence and fit.sequence is not None:
        record["sequence"] = {k: v for k, v in fit.sequence.items() if k != "grid"}
        record["sequence_settings"] = asdict(fit.config.sequence_params())
    return fit.config, record


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
    t0 = time.perf_counter()
    plan_, bank, times = pseudo_plan_bank(references, metadata, cache, seed=seed)
    fitted, rec = pseudo_fit(config, bank, seed=seed)
    times["acceptance_s"] = rec.pop("acceptance_s")
    times["total_s"] = time.perf_counter() - t0
    record = {"sample": plan_.summary(), **rec, "time_s": times}
    return fitted, record


def flags(policy: Policy, answers: Any, sequence: bool) -> np.ndarray:
    """Per answer: accepted by ``policy`` (the one policy, :func:`apply_acceptance`)."""
    return np.array(apply_acceptance(policy, answers, sequence=sequence)["accepted_answers"], bool)


def sign_tests(
    per_variant: Mapping[str, np.ndarray], pairs: Sequence[tuple[str, str]] = PAIRS
) -> dict[str, dict[str, Any]]:
    """Paired sign tests of ``pairs`` on ``per_variant``'s flags (same frames)."""
    return {
        f"{a} vs {b}": paired_test(per_variant[a], per_variant[b])
        for a, b in pairs
        if a in per_variant and b in per_variant
    }


def route_flags(
    policies: Mapping[str, Policy],
    answers: Mapping[str, Any],
    own: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Per mode, per variant: accepted-and-right in the map (``single``, ``sequence``),
    accepted-and-wrong in the map (``single_wrong``, ``sequence_wrong``) and accepted for the
    foreign frames (``foreign_single``, ``foreign_sequence``). A variant in ``own`` is
    decided on its own answers (the same frames, e.g. driven with other filter settings)."""
    own = own or {}
    out: dict[str, dict[str, np.ndarray]] = {}
    for mode in MODES:
        seq = mode == "sequence"
        out[mode], out[f"{mode}_wrong"], out[f"foreign_{mode}"] = {}, {}, {}
        for v, p in policies.items():
            ans = own.get(v, answers)
            x = flags(p, ans[mode], seq)
            right = ans[mode].correct
            out[mode][v] = x & right
            out[f"{mode}_wrong"][v] = x & ~right
            out[f"foreign_{mode}"][v] = flags(p, ans[f"foreign_{mode}"], seq)
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


def parse_cases(text: str, routes: Sequence[str] = tuple(ROUTES)) -> list[tuple[str, str]]:
    """``--found``'s ``ROUTE=HIERARCHY,...`` as (route, hierarchy) pairs, in order."""
    out: list[tuple[str, str]] = []
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        route, sep, hierarchy = item.partition("=")
        route, hierarchy = route.strip(), hierarchy.strip()
        if not sep or not route or not hierarchy:
            raise ValueError(f"--found takes ROUTE=HIERARCHY items, not {item!r}")
        if route not in routes:
            raise ValueError(f"unknown route {route!r} (one of {', '.join(routes)})")
        if (route, hierarchy) in out:
            raise ValueError(f"{item!r} given twice")
        out.append((route, hierarchy))
    if not out:
        raise ValueError("--found names no ROUTE=HIERARCHY")
    return out


def profile_methods(config: HierarchyConfig) -> tuple[str, ...]:
    """The methods a :class:`hmpf.confidence.ReferenceProfile` of ``config`` holds: its
    tier-1 global methods."""
    if not config.tiers:
        return ()
    return tuple(
        m
        for m in config.tiers[0].methods
        if issubclass(get_method_class(config.method_spec(m)[0]), GlobalMethod)
    )


def undefined_features(features: Sequence[str], config: HierarchyConfig) -> list[str]:
    """The features of a model that ``config``'s answers would not carry: unknown names, and
    the profile features (``ref_z``, ``sequence_ref_z``) when its tier 1 has no global
    method (the profile is empty and they read 0 for every answer)."""
    bad = [f for f in features if f not in ALL_FEATURES]
    if not profile_methods(config):
        bad += [f for f in features if f in PROFILE_FEATURES]
    return bad


def baseline_flags(baseline: Mapping[str, Any], route: str) -> dict[str, np.ndarray] | None:
    """The ``shipped`` variant's flags on ``route`` in a record of this bench's first mode
    (keys as :func:`route_flags`'), or None when the record lacks the route."""
    entry = baseline.get("routes", {}).get(route)
    if entry is None:
        return None
    fl = entry["flags"]
    kinds = ("single", "single_wrong", "sequence", "sequence_wrong")
    kinds += ("foreign_single", "foreign_sequence")
    return {k: np.asarray(fl[f"{k}:shipped"], bool) for k in kinds}


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
        lines += [variant_row(name, v, entry[v], ece) for v in VARIANTS]
    return "\n".join(lines)


def variant_row(
    label: str, variant: str, figures: Mapping[str, Any], ece: Callable[[Mapping[str, Any]], str]
) -> str:
    """One table row of a variant's single and sequence figures, in the map and off it
    (``ece`` formats a mode's calibration entry)."""
    s, q = figures["single"], figures["sequence"]
    return (
        f"| {label} ({s['n']}) | {variant} | {s['accepted']:.3f} ({_f(s['precision'])}) | "
        f"{ece(s['calibration'])} | {q['rule']} | {q['accepted']:.3f} "
        f"({_f(q['precision'])}) | {ece(q['calibration'])} | "
        f"{q['flips_per_100']:.1f} | {s['foreign']['accepted']:.3f} / "
        f"{_f(s['foreign']['mean_p'])} | {q['foreign']['accepted']:.3f} / "
        f"{_f(q['foreign']['mean_p'])} |"
    )


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

# -- a hierarchy without shipped models (--found) ------------------------------------------------


def hierarchy_of(
    route: str, spec: str, seed: int, cache: FeatureCache, auto_record: str | Path
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """The hierarchy ``spec`` names for ``route`` (without acceptance) and where it comes
    from: ``auto``: the one :func:`auto` chooses on the route's training part as
    ``bench/auto_config.py`` runs it (its record ``auto_record`` when it holds the route,
    else run here with ``seed``); else a preset's name or a YAML file."""
    if spec != "auto":
        config = load_config(spec)
        source: dict[str, Any] = {"from": spec}
    else:
        rec = json.loads(Path(auto_record).read_text()) if Path(auto_record).is_file() else {}
        entry = rec.get("routes", {}).get(route)
        if entry is not None:
            config = HierarchyConfig.model_validate(entry["auto_reasons"]["config"])
            source = {
                "from": str(Path(auto_record).relative_to(ROOT))
                if Path(auto_record).is_relative_to(ROOT)
                else str(auto_record),
                "date": entry.get("date", rec.get("date")),
                "commit": entry.get("commit", rec.get("commit")),
                "why": entry["auto_reasons"].get("chosen", {}).get("why"),
            }
        else:
            train, _ = route_parts(route, str(dataset_root()), None)
            meta = {"sequence": stretch_sequence(len(train.reference), BLOCKS.get(route, 20))}
            print(f"[{route}] auto on {len(train.reference)} training references", flush=True)
            t0 = time.perf_counter()
            result = auto(train.reference, meta, seed=seed, cache=cache)
            config = result.config
            source = {
                "from": f"auto run here (seed {seed}, {len(train.reference)} references)",
                "why": result.reasons["chosen"]["why"],
                "auto_s": time.perf_counter() - t0,
            }
    config = config.model_copy(update={"acceptance": None})
    label = describe(
        [t.methods for t in config.tiers], [t.k for t in config.tiers], config.tier_weights
    )
    source |= {
        "name": config.name,
        "hierarchy": label,
        "digest": config.digest(),
        "ships_models": config.digest() in shipped_acceptance(),
    }
    return config, source


def bank_pool(config: HierarchyConfig) -> HierarchyConfig:
    """The pool the pseudo bank is built over: :func:`auto_pool` when ``config`` runs on it
    (what auto fits on), else ``config``'s own methods."""
    pool = auto_pool()
    try:
        check_compatible(config, pool)
    except ConfigError:
        return config.model_copy(update={"acceptance": None})
    return pool


def found_case(
    name: str,
    spec: str,
    args: Any,
    cache: FeatureCache,
    carried: Policy,
    baseline: Mapping[str, Any],
    t0: float,
) -> tuple[dict[str, Any], dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """One route with one hierarchy: the three variants' figures, their answers (by variant)
    and flags (keys as :func:`route_flags`', the baseline's added)."""
    config, source = hierarchy_of(name, spec, args.seed, cache, args.auto_record)
    print(f"[{name} {spec}] {source['hierarchy']} ({source['digest'][:12]})", flush=True)
    route = Route(name, config, cache, args.foreign, limit_of(name, args.nordland_frames))
    print(f"[{name} {spec}] banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    refs = route.train_data.reference
    meta = {"sequence": stretch_sequence(len(refs), BLOCK)}
    pool = bank_pool(config)
    plan_, bank, times = pseudo_plan_bank(refs, meta, cache, seed=args.seed, pool=pool)
    params = config.sequence_params()
    single_cfg, single_rec = pseudo_fit(config, bank, seed=args.seed)
    seq_cfg, seq_rec = pseudo_fit(config, bank, seed=args.seed, sequence=True)
    seq_params = seq_cfg.sequence_params()
    pseudo = Policy.of(single_cfg.acceptance, lock_mass=params.lock_mass)
    policies = {
        "pseudo": pseudo,
        "pseudo-seq": Policy.of(seq_cfg.acceptance, lock_mass=seq_params.lock_mass),
        "pseudo+default-seq": combine(pseudo, carried),
    }
    print(f"[{name} {spec}] pseudo fits ({time.perf_counter() - t0:.0f} s)", flush=True)
    answers = route_answers(route, config, params)
    own = {"pseudo-seq": route_answers(route, config, seq_params)}
    gp = name.startswith("gp_")
    carried_features = list(carried.sequence_model.features) if carried.sequence_model else []
    entry: dict[str, Any] = {
        "route": name,
        "hierarchy": source,
        "n_train_references": len(refs),
        "n_test": route.n_test,
        "n_foreign": route.n_foreign,
        "right_single": float(answers["single"].correct.mean()),
        "right_sequence": float(answers["sequence"].correct.mean()),
        "pseudo_bank": {
            "pool": pool.name,
            "sample": plan_.summary(),
            "time_s": times,
            "recall_at_1": bank.run(config).recall_at_1,
        },
        "pseudo_fit": single_rec,
        "pseudo_seq_fit": seq_rec,
        "carried": {
            "preset": CARRIED,
            "features": carried_features,
            "profile_methods": list(profile_methods(config)),
            "undefined_features": undefined_features(carried_features, config),
        },
        "sequence_params": {
            "pseudo": asdict(params),
            "pseudo-seq": asdict(seq_params),
        },
    }
    for v, policy in policies.items():
        entry[v] = {"policy": policy.describe(), **measure(policy, own.get(v, answers), gp)}
    fl = route_flags(policies, answers, own)
    base = baseline_flags(baseline, name)
    if base is not None:
        for k, x in base.items():
            fl[k][BASELINE] = x
        b = baseline["routes"][name]["shipped"]
        entry[BASELINE] = {
            "digest": baseline.get("digest"),
            "single": single_figures(b["single"]),
            "sequence": {
                "accepted": b["sequence"]["accepted"],
                "precision": b["sequence"]["precision"],
                "ece": b["sequence"]["calibration"].get("ece"),
                "flips_per_100": b["sequence"]["flips_per_100"],
                "foreign_accepted": b["sequence"]["foreign"]["accepted"],
                "foreign_mean_p": b["sequence"]["foreign"]["mean_p"],
                "right": b["sequence"]["right"],
            },
        }
    entry["sign_tests"] = {k: sign_tests(per, found_pairs()) for k, per in fl.items()}
    entry["flags"] = {
        "right_single": answers["single"].correct.astype(int).tolist(),
        "right_sequence": answers["sequence"].correct.astype(int).tolist(),
        **{f"{k}:{v}": x.astype(int).tolist() for k, per in fl.items() for v, x in per.items()},
    }
    print(f"[{name} {spec}] done ({time.perf_counter() - t0:.0f} s)", flush=True)
    all_answers = {v: own.get(v, answers) for v in FOUND_VARIANTS}
    return entry, all_answers, fl


def found_pairs() -> tuple[tuple[str, str], ...]:
    """The sign tests of ``--found``: the variants' pairs, then each against the baseline."""
    return FOUND_PAIRS + tuple((v, BASELINE) for v in FOUND_VARIANTS)


def found_main(args: Any, t0: float) -> int:
    cases = parse_cases(args.found)
    cache = FeatureCache(default_cache_dir())
    carried = Policy.of(
        load_config(CARRIED).acceptance,
        lock_mass=load_config(CARRIED).sequence_params().lock_mass,
    )
    base_path = Path(args.baseline)
    baseline = json.loads(base_path.read_text()) if base_path.is_file() else {}
    same = baseline.get("arguments", {})
    if baseline and (
        same.get("foreign") != args.foreign or same.get("nordland_frames") != args.nordland_frames
    ):
        print(f"{base_path}: other --foreign / --nordland-frames; no baseline", flush=True)
        baseline = {}
    report: dict[str, Any] = {
        **provenance(None, None, args),
        "note": NOTE,
        "goals": GOALS,
        "variants": {
            "pseudo": "(b) auto's fit on pseudo-queries of the training part's references "
            "(single-frame model; sequence: lock rule): what a found hierarchy ships with",
            "pseudo-seq": "(d) fit_config_acceptance(sequence=True, model=True, outside=True) "
            "on the same pseudo bank: tuned filter settings and a sequence model",
            "pseudo+default-seq": f"(e) (b)'s single-frame model with the {CARRIED!r} "
            "preset's shipped sequence model and thresholds",
            BASELINE: "the default preset (its own hierarchy) with its shipped acceptance on "
            "the same frames, from --baseline",
        },
        "baseline": {
            "path": str(base_path.relative_to(ROOT)) if base_path.is_relative_to(ROOT) else None,
            "digest": baseline.get("digest"),
            "date": baseline.get("date"),
            "commit": baseline.get("commit"),
        }
        if baseline
        else None,
        "split_block": BLOCK,
        "foreign_frames": args.foreign,
        "nordland_frames": args.nordland_frames or "all",
        "auto_defaults": {
            k: AUTO_DEFAULTS[k]
            for k in ("max_references", "max_queries", "tolerance", "radius_m", "target_precision")
        },
        "cases": {},
    }
    by_spec: dict[str, dict[str, dict[str, list[np.ndarray]]]] = {}
    for name, spec in cases:
        entry, _, fl = found_case(name, spec, args, cache, carried, baseline, t0)
        report["cases"][f"{name}={spec}"] = entry
        for k, per in fl.items():
            for v, x in per.items():
                by_spec.setdefault(spec, {}).setdefault(k, {}).setdefault(v, []).append(x)
    report["pooled_by_hierarchy"] = {
        spec: {
            "routes": [n for n, s in cases if s == spec],
            "sign_tests": {
                k: sign_tests({v: np.concatenate(xs) for v, xs in per.items()}, found_pairs())
                for k, per in fl_.items()
                if all(len(xs) == len(next(iter(per.values()))) for xs in per.values())
            },
        }
        for spec, fl_ in by_spec.items()
        if sum(s == spec for _, s in cases) > 1
    }
    report["digests"] = {k: e["hierarchy"]["digest"] for k, e in report["cases"].items()}
    report["wall_s"] = time.perf_counter() - t0
    out = write_json(args.out, strip(report))
    text = found_markdown(report)
    Path(args.out).with_suffix(".md").write_text(text + "\n")
    print(text)
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


def found_table(report: Mapping[str, Any]) -> str:
    """Markdown: per case and variant (the baseline last), both modes in the map and off it."""
    lines = [
        "| route = hierarchy (test queries) | acceptance | single accepted (prec.) | "
        "single ECE | sequence rule | sequence accepted (prec.) | seq. ECE | flips / 100 | "
        "foreign single accepted / mean p | foreign seq. accepted / mean p |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, e in report["cases"].items():
        lines += [variant_row(key, v, e[v], lambda cal: _f(cal.get("ece"))) for v in FOUND_VARIANTS]
        b = e.get(BASELINE)
        if b is not None:
            s, q = b["single"], b["sequence"]
            lines.append(
                f"| {key} | {BASELINE} (default's hierarchy) | {s['accepted']:.3f} "
                f"({_f(s['precision'])}) | {_f(s['ece'])} | p_correct | {q['accepted']:.3f} "
                f"({_f(q['precision'])}) | {_f(q['ece'])} | {q['flips_per_100']:.1f} | "
                f"{s['foreign_accepted']:.3f} / {_f(s['foreign_mean_p'])} | "
                f"{q['foreign_accepted']:.3f} / {_f(q['foreign_mean_p'])} |"
            )
    return "\n".join(lines)


def fits_table(report: Mapping[str, Any]) -> str:
    """Markdown: per case, the hierarchy, its test recall and what the pseudo fits gave."""
    lines = [
        "| route = hierarchy | config digest | hierarchy | test right single / seq. | "
        "pseudo-query recall@1 | (b) single threshold | (d) filter lock mass | "
        "(d) sequence model threshold | (e) features undefined |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key, e in report["cases"].items():
        h = e["hierarchy"]
        single = e["pseudo_fit"]["confidence"].get("single", {})
        seq = e["pseudo_seq_fit"]["confidence"].get("sequence", {})
        lock = (e["pseudo_seq_fit"].get("sequence_settings") or {}).get("lock_mass")
        seq_thr = seq.get("threshold") if "skipped" not in seq else f"skipped: {seq['skipped']}"
        lines.append(
            f"| {key} | `{h['digest'][:12]}` | {h['hierarchy']} | {e['right_single']:.3f} / "
            f"{e['right_sequence']:.3f} | {e['pseudo_bank']['recall_at_1']:.3f} | "
            f"{_f(single.get('threshold'))} | {_f(lock)} | "
            f"{seq_thr if isinstance(seq_thr, str) else _f(seq_thr)} | "
            f"{', '.join(e['carried']['undefined_features']) or 'none'} |"
        )
    return "\n".join(lines)


def found_tests_table(report: Mapping[str, Any]) -> str:
    """Markdown: the sign tests (wins / losses, p) per case and pooled by hierarchy."""
    keys = [f"{a} vs {b}" for a, b in found_pairs()]
    what = {
        "sequence": "seq.: accepted and right",
        "sequence_wrong": "seq.: accepted and wrong",
        "foreign_sequence": "foreign seq.: accepted",
        "single": "single: accepted and right",
        "single_wrong": "single: accepted and wrong",
        "foreign_single": "foreign single: accepted",
    }
    rows = {k: e["sign_tests"] for k, e in report["cases"].items()}
    rows |= {f"pooled {s}": p["sign_tests"] for s, p in report["pooled_by_hierarchy"].items()}
    shown = [k for k in keys if any(k in t.get("sequence", {}) for t in rows.values())]
    lines = [
        "| case | flags | " + " | ".join(shown) + " |",
        "|---|---|" + "---|" * len(shown),
    ]
    for name, tests in rows.items():
        for kind, label in what.items():
            t = tests.get(kind, {})
            cells = [
                f"{t[k]['wins']} / {t[k]['losses']}, p = {t[k]['p']:.2g}" if k in t else "n/a"
                for k in shown
            ]
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def found_markdown(report: Mapping[str, Any]) -> str:
    digests = ", ".join(
        f"{k}: `{e['hierarchy']['digest'][:12]}`" for k, e in report["cases"].items()
    )
    base = report.get("baseline") or {}
    head = (
        f"Hierarchies without shipped models ({digests}); {report['machine']}, "
        f"{report['date']}, commit {str(report.get('commit'))[:10]}. Test parts, +-2 frames; "
        f"{report['foreign_frames']} foreign frames per map; Nordland's first "
        f"{report['nordland_frames']} frames. Baseline: the default preset "
        f"(`{str(base.get('digest'))[:12]}`) with its shipped acceptance, from "
        f"`{base.get('path')}` (commit {str(base.get('commit'))[:10]})."
    )
    return "\n\n".join(
        [
            head,
            fits_table(report),
            found_table(report),
            "Paired sign tests (wins / losses of the first against the second, two-sided p):",
            found_tests_table(report),
        ]
    )


def build_parser() -> Any:
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
    ap.add_argument(
        "--found",
        default=None,
        help="ROUTE=HIERARCHY,...: measure hierarchies without shipped models instead "
        "(HIERARCHY: 'auto', a preset or a YAML file; see the module docstring)",
    )
    ap.add_argument(
        "--auto-record",
        default=str(AUTO_CONFIG_OUT),
        help="with --found ROUTE=auto: bench/auto_config.py's record holding the route's "
        "choice (else auto runs here)",
    )
    ap.add_argument(
        "--baseline",
        default=str(DEFAULT_OUT),
        help="with --found: this bench's record for the default preset (its shipped flags)",
    )
    add_json(ap, "--out", default=None, help=f"default {DEFAULT_OUT} ({FOUND_OUT} with --found)")
    return ap


def measure_route(
    route: Route,
    args: Any,
    config: HierarchyConfig,
    shipped: Policy,
    params: Any,
    cache: FeatureCache,
    t0: float,
) -> tuple[dict[str, Any], dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """One route: the three variants' figures, the other seeds' single-frame figures and the
    sign tests. Returns the route's entry, its answers and its per-variant flags."""
    name = route.name
    refs = route.train_data.reference
    meta = {"sequence": stretch_sequence(len(refs), BLOCK)}
    fitted, fit_record = pseudo_acceptance(config, refs, meta, cache, seed=args.seed)
    pseudo = Policy.of(fitted.acceptance, lock_mass=params.lock_mass)
    print(f"[{name}] pseudo fit ({time.perf_counter() - t0:.0f} s)", flush=True)
    policies = {"shipped": shipped, "pseudo": pseudo, "pseudo+seq": combine(pseudo, shipped)}
    answers = route_answers(route, config, params)
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
            "digest": config.digest(),
            "policy": policy.describe(),
            **measure(policy, answers, gp),
        }
    entry["pseudo_other_seeds"] = {}
    for seed in [int(x) for x in args.other_seeds.split(",") if x.strip()]:
        other, rec = pseudo_acceptance(config, refs, meta, cache, seed=seed)
        pol = Policy.of(other.acceptance, lock_mass=params.lock_mass)
        entry["pseudo_other_seeds"][str(seed)] = {
            "single_threshold": pol.model_threshold,
            "single": single_figures(measure(pol, answers, gp)["single"]),
            "pseudo_fit": rec,
        }
        print(f"[{name}] pseudo fit, seed {seed} ({time.perf_counter() - t0:.0f} s)")
    fl = route_flags(policies, answers)
    entry["sign_tests"] = {k: sign_tests(per) for k, per in fl.items()}
    entry["flags"] = {
        "right_single": answers["single"].correct.astype(int).tolist(),
        "right_sequence": answers["sequence"].correct.astype(int).tolist(),
        **{f"{k}:{v}": x.astype(int).tolist() for k, per in fl.items() for v, x in per.items()},
    }
    return entry, answers, fl


def pooled_report(
    routes: Mapping[str, Mapping[str, Any]],
    answers: dict[str, dict[str, Any]],
    all_flags: Mapping[str, Mapping[str, list[np.ndarray]]],
) -> dict[str, Any]:
    """The routes pooled: sign tests over every route's flags, ECE and counts per variant
    (all routes, and Gardens Point's alone)."""
    out: dict[str, Any] = {
        "sign_tests": {
            k: sign_tests({v: np.concatenate(xs) for v, xs in per.items()})
            for k, per in all_flags.items()
        }
    }
    for v in VARIANTS:
        runs = {name: entry[v] for name, entry in routes.items()}
        groups = {"all": list(runs), "gardens_point": [n for n in runs if n.startswith("gp_")]}
        out[v] = {
            "ece": pooled(runs, answers),
            "counts": {
                g: {m: pooled_counts([runs[n][m] for n in names]) for m in MODES}
                for g, names in groups.items()
            },
        }
    return out


def main() -> int:
    args = build_parser().parse_args()
    t0 = time.perf_counter()
    if args.found:
        args.out = args.out or str(FOUND_OUT)
        return found_main(args, t0)
    args.out = args.out or str(DEFAULT_OUT)
    shipped_config, config, shipped = out_of_the_box(args.config)
    params = shipped_config.sequence_params()
    cache = FeatureCache(default_cache_dir())
    report: dict[str, Any] = {
        **provenance(args.config, config, args),
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
    all_flags: dict[str, dict[str, list[np.ndarray]]] = {}
    for name in args.routes.split(","):
        route = Route(name, config, cache, args.foreign, limit_of(name, args.nordland_frames))
        print(f"[{name}] banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
        entry, answers[name], fl = measure_route(route, args, config, shipped, params, cache, t0)
        for k, per in fl.items():
            for v, x in per.items():
                all_flags.setdefault(k, {}).setdefault(v, []).append(x)
        report["routes"][name] = entry
        print(f"[{name}] done ({time.perf_counter() - t0:.0f} s)", flush=True)
    report["pooled"] = pooled_report(report["routes"], answers, all_flags)
    report["wall_s"] = time.perf_counter() - t0
    out = write_json(args.out, strip(report))
    text = markdown(report)
    Path(args.out).with_suffix(".md").write_text(text + "\n")
    print(text)
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
