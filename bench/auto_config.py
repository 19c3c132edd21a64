"""The automatic choice from the references alone against the default, the oracle preset and
hmpf-calibrate with real queries, on every route.

    python -m bench.auto_config [--protocols gp_dl_dr ...] [--seed 0] [--nordland-frames N] \\
        [--out docs/experiments/auto_config/auto_config.json]

Per route (Gardens Point's three protocols, Nordland summer -> winter), the route is split as
``hmpf-calibrate`` splits it (``blocks``: alternating stretches of 20 frames, Nordland 100 as
``calibrated/nordland_handcrafted`` and the ``thumbnails`` figures were measured), +-2 frames:

* **auto**: :func:`hmpf.evaluation.auto.auto` on the *training part's references only* (with
  each stretch as its own ``sequence``, as an operator's metadata would give the drives): it
  never sees a query, and nothing of the test part;
* **default**: the ``default`` preset as it ships;
* **oracle**: the bundled preset (:data:`ORACLE_PRESETS`) with the best *test* recall, chosen
  afterwards with the test queries (a bound no rule that chooses beforehand can beat);
* **calibrate**: :func:`hmpf.evaluation.calibrate.calibrate` with the real training queries
  on the same pool, search space, budget and cost model as auto (``hmpf-calibrate --pool``
  of the automatic pool): the same search, with real queries instead of pseudo-queries.

Each is measured on the test part (recall@1 with ``bench.one_pass.correct_flags``: methods
fitted on the test part's references), with paired sign tests of auto against each. Then, how
well pseudo-query recall predicts real-query recall: Spearman's rank correlation, across
auto's candidates and across a spread of the hierarchies its search tried (evenly along its
ranking), between their recall on all pseudo-queries and on the test part's (and the training
part's) real queries.

Goals (stated before the run): auto is not significantly worse than the default (sign test,
p < 0.05), within 3 points of the oracle, and >= 0.58 on Nordland. Writes the JSON record
(provenance from :mod:`bench.harness`) and a Markdown printout beside it (``.md``).

``--time N [N ...]`` measures instead how long the choice takes (what it adds to an index
build): :func:`hmpf.evaluation.auto.choose_config` (the size rule off: the search) on the
first N Nordland references (summer, winter, then their mirror images), each with an empty
feature cache (every pool feature extracted), as one process on this
machine; the time per step, the sample sizes and the load average, written to ``--out``.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.stats import spearmanr

from bench.harness import (
    NORDLAND,
    PROTOCOLS,
    ROOT,
    add_data,
    add_json,
    add_protocols,
    machine,
    parser,
    protocol_data,
    provenance,
    write_json,
)
from bench.one_pass import correct_flags
from bench.pages import auto_config_tables
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import list_images
from hmpf.evaluation.auto import AutoResult, auto, auto_pool, choose_config
from hmpf.evaluation.calibrate import SearchSpace, calibrate
from hmpf.evaluation.data import EvalData
from hmpf.evaluation.metrics import paired_test
from hmpf.evaluation.study import CostModel, ScoreBank, split_data
from hmpf.features import FeatureCache

#: The bundled presets a user picks among (the calibration pools and the calibrated/* fits of
#: these very routes left out); the oracle is the best of them on each test part.
ORACLE_PRESETS = (
    "default",
    "default-lite0",
    "fast",
    "netvlad-lite1",
    "handcrafted",
    "handcrafted-faithful",
    "paper-berlin",
    "paper-nordland",
    "single-tier",
    "thumbnails",
    "all-global",
    "all-methods",
)
#: Frames per stretch of the blocks split, per route.
BLOCKS = {"nordland_s_w": 100}
#: Goals, fixed before the run.
ORACLE_MARGIN = 0.03
NORDLAND_FLOOR = 0.58
ALPHA = 0.05
#: Hierarchies of the search's ranking whose real recall is measured for the correlation.
SPREAD = 60
DEFAULT_OUT = ROOT / "docs" / "experiments" / "auto_config" / "auto_config.json"


def route_parts(name: str, datasets: str, frames: int | None) -> tuple[EvalData, EvalData]:
    """The route's training and test parts (the first ``frames`` frames when given)."""
    data = protocol_data(name, datasets, 2)
    if frames is not None and frames < len(data.reference):
        data = EvalData(
            data.reference[:frames],
            data.query[:frames],
            data.gt[:frames, :frames],
            data.ground_truth,
        )
    return split_data(data, block=BLOCKS.get(name, 20))


def stretch_sequence(n: int, block: int) -> np.ndarray:
    """A training part's references' ``sequence``: one value per stretch of the split (its
    frames are consecutive along the route; two stretches are not)."""
    return np.array([f"stretch{i // block}" for i in range(n)], dtype=object)


def spearman(x: list[float], y: list[float]) -> float | None:
    """Spearman's rank correlation (ties averaged), None when either side is constant."""
    if len(x) < 3 or len(set(x)) < 2 or len(set(y)) < 2:
        return None
    return float(spearmanr(x, y).statistic)


def _costs_for(costs: CostModel, n_db: int) -> CostModel:
    return CostModel(costs.units, costs.method_units, costs.match, costs.fusion_ms, n_db)


def correlation(result: AutoResult, train_bank: ScoreBank, test_bank: ScoreBank) -> dict[str, Any]:
    """Pseudo-query recall against real recall (test and training parts) of auto's
    candidates and of :data:`SPREAD` hierarchies spread along its search's ranking (empty
    where the size rule chose without pseudo-queries)."""
    if result.bank is None:
        return {}
    pool = auto_pool()
    ranked = result.ranked
    pick = np.unique(np.linspace(0, len(ranked) - 1, min(SPREAD, len(ranked))).round().astype(int))
    sets: dict[str, list[tuple[str, HierarchyConfig]]] = {
        "candidates": [(c.label, c.config) for c in result.candidates],
        "spread": [(ranked[int(i)].label(), ranked[int(i)].config(pool)) for i in pick],
    }
    out: dict[str, Any] = {}
    for key, items in sets.items():
        rows: list[dict[str, Any]] = []
        for label, cfg in items:
            rows.append(
                {
                    "hierarchy": label,
                    "pseudo": result.bank.run(cfg).recall_at_1,
                    "real_test": test_bank.run(cfg).recall_at_1,
                    "real_train": train_bank.run(cfg).recall_at_1,
                }
            )
        p = [r["pseudo"] for r in rows]
        out[key] = {
            "n": len(rows),
            "spearman_test": spearman(p, [r["real_test"] for r in rows]),
            "spearman_train": spearman(p, [r["real_train"] for r in rows]),
            "rows": rows,
        }
    return out


def run_route(name: str, args: Any, cache: FeatureCache) -> dict[str, Any]:
    """Everything measured on one route (see the module docstring)."""
    t_route = time.perf_counter()
    frames = args.nordland_frames if name == "nordland_s_w" else None
    train, test = route_parts(name, args.datasets, frames)
    block = BLOCKS.get(name, 20)
    meta = {"sequence": stretch_sequence(len(train.reference), block)}
    print(f"[{name}] auto on {len(train.reference)} training references", flush=True)
    t0 = time.perf_counter()
    result = auto(train.reference, meta, seed=args.seed, cache=cache, workers=args.workers)
    auto_s = time.perf_counter() - t0
    chosen = result.reasons["chosen"]
    print(
        f"[{name}] auto chose {chosen['hierarchy']} ({auto_s:.0f} s): {chosen['why']}", flush=True
    )
    # the size rule chose without pseudo-queries: the search it skipped is measured beside
    # it (its choice's real recall and the rank correlation), the evidence for the rule
    searched = result
    if result.bank is None:
        print(f"[{name}] auto without the size rule", flush=True)
        searched = auto(
            train.reference,
            meta,
            seed=args.seed,
            cache=cache,
            workers=args.workers,
            small_side=None,
        )
    pool = auto_pool()
    assert result.costs is not None
    train_bank = ScoreBank.build(pool, train, cache=cache, workers=args.workers)
    test_bank = ScoreBank.build(pool, test, cache=cache, workers=args.workers)
    print(f"[{name}] calibrate with real training queries", flush=True)
    t0 = time.perf_counter()
    cal_config, cal_report = calibrate(
        pool,
        train_bank,
        None,
        SearchSpace(tuple(pool.method_ids)),
        budget_ms=result.reasons["budget_ms"],
        seed=args.seed,
        costs=_costs_for(result.costs, len(train.reference)),
        model=False,
        outside=False,
    )
    cal_s = time.perf_counter() - t0
    flags: dict[str, np.ndarray] = {}
    configs: dict[str, HierarchyConfig] = {"auto": result.config, "calibrate": cal_config}
    if searched is not result:
        configs["auto_without_rule"] = searched.config
    measured = [p for p in ORACLE_PRESETS if p not in args.skip_presets]
    configs |= {p: load_config(p) for p in measured}
    for key, cfg in configs.items():
        t0 = time.perf_counter()
        flags[key] = correct_flags(cfg, test, cache)
        print(
            f"[{name}] {key}: test recall@1 {flags[key].mean():.3f} "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    presets = {p: float(flags[p].mean()) for p in measured}
    oracle = max(measured, key=lambda p: (presets[p], -ORACLE_PRESETS.index(p)))
    recall = {k: float(f.mean()) for k, f in flags.items()}
    vs = {
        "default": paired_test(flags["auto"], flags["default"]),
        "oracle": paired_test(flags["auto"], flags[oracle]),
        "calibrate": paired_test(flags["auto"], flags["calibrate"]),
    }
    lost = vs["default"]["losses"] > vs["default"]["wins"] and vs["default"]["p"] < ALPHA
    goals = {
        "not_worse_than_default": not lost,
        "within_3_points_of_oracle": recall["auto"] >= presets[oracle] - ORACLE_MARGIN - 1e-12,
    }
    if name == "nordland_s_w":
        goals["nordland_at_least_0.58"] = recall["auto"] >= NORDLAND_FLOOR
    print(f"[{name}] correlation of pseudo and real recall", flush=True)
    corr = correlation(searched, train_bank, test_bank)
    return {
        "route": name,
        "split_block": block,
        "frames": frames,
        "n_train_reference": len(train.reference),
        "n_test_query": len(test.query),
        "recall_at_1": recall,
        "digests": {k: c.digest() for k, c in configs.items()},
        "auto_hierarchy": chosen["hierarchy"],
        "calibrate_hierarchy": cal_report["train"]["winner"]["hierarchy"],
        "oracle": oracle,
        "presets": presets,
        "presets_skipped": [p for p in ORACLE_PRESETS if p in args.skip_presets],
        "vs": vs,
        "goals": goals,
        "correlation": corr,
        "auto_reasons": result.reasons,
        "auto_without_rule": None
        if searched is result
        else {
            "hierarchy": searched.reasons["chosen"]["hierarchy"],
            "why": searched.reasons["chosen"]["why"],
            "vs_auto": paired_test(flags["auto_without_rule"], flags["auto"]),
        },
        "calibrate_train_recall_at_1": cal_report["train"]["winner"]["recall_at_1"],
        "flags": {k: f.astype(int).tolist() for k, f in flags.items()},
        "time_s": {"auto": auto_s, "calibrate": cal_s, "route": time.perf_counter() - t_route},
    }


def markdown(record: dict[str, Any]) -> str:
    """The printout: one table of the test recall per route, the tests and the goals, one of
    the rank correlations (:func:`bench.pages.auto_config_tables`)."""
    head = [
        "# The automatic choice against the default, the oracle preset and hmpf-calibrate",
        "",
        f"{record['machine']}; commit {str(record.get('commit'))[:12]}; {record['date']}; "
        f"seed {record['arguments']['seed']}.",
        "",
    ]
    return "\n".join(head) + auto_config_tables(record)


def time_choice(sizes: list[int], args: Any) -> dict[str, Any]:
    """``--time``: the choice on the first N Nordland references, cold cache: the summer
    drive, then the winter drive (a map of two drives, each its own ``sequence``, for N
    above one drive's 3,576; past both, their mirror images as a third, :func:`mirror_images`).
    The size rule is off: its search is what a build of a camera's frames waits for
    (thumbnails take the rule's preset in well under a second)."""
    if max(sizes) > 4 * 3576:
        raise SystemExit(f"--time {max(sizes)}: at most {4 * 3576} (two drives and their mirrors)")
    drives = [list_images(Path(args.datasets) / folder) for folder in NORDLAND]
    refs: list[Path] = [p for d in drives for p in d]
    drive = np.array([name for name, d in zip(NORDLAND, drives, strict=True) for _ in d])
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="hmpf-auto-mirror-") as mirror_dir:
        more = max(sizes) - len(refs)
        if more > 0:  # past both drives: their mirror images, a third "drive"
            mirrored = mirror_images(refs[:more], Path(mirror_dir))
            refs += mirrored
            drive = np.concatenate([drive, np.array(["mirrored"] * len(mirrored))])
        for n in sizes:
            out[str(n)] = _time_one(refs[:n], drive[:n], args)
    return out


def mirror_images(paths: list[Path], folder: Path) -> list[Path]:
    """Each image flipped left to right, written to ``folder`` (distinct images of the same
    size and statistics, for a map larger than the data sets)."""
    out = []
    for i, p in enumerate(paths):
        dst = folder / f"mirror{i:05d}_{p.name}"
        cv2.imwrite(str(dst), cv2.flip(cv2.imread(str(p)), 1))
        out.append(dst)
    return out


def _time_one(refs: list[Path], drive: np.ndarray, args: Any) -> dict[str, Any]:
    """One ``--time`` row: the choice on ``refs``, cold cache."""
    n = len(refs)
    with tempfile.TemporaryDirectory(prefix="hmpf-auto-time-") as tmp:
        load = os.getloadavg()
        t0 = time.perf_counter()
        _, reasons = choose_config(
            refs,
            {"sequence": drive},
            seed=args.seed,
            cache=FeatureCache(tmp),
            workers=args.workers,
            small_side=None,  # the search, as a camera's frames run it (thumbnails skip it)
        )
        wall = time.perf_counter() - t0
    print(f"{n} references: {wall:.0f} s ({reasons['time_s']})", flush=True)
    return {
        "references": n,
        "mirrored": int(np.sum(drive == "mirrored")),
        "wall_s": wall,
        "steps_s": reasons["time_s"],
        "sample": reasons["sample"],
        "chosen": reasons["chosen"]["hierarchy"],
        "load_start": list(load),
        "load_end": list(os.getloadavg()),
    }


def timing_markdown(record: dict[str, Any]) -> str:
    """The ``--time`` printout: one row per map size."""
    lines = [
        "# How long the automatic choice takes",
        "",
        f"Latest run: {record['machine']}; commit {str(record.get('commit'))[:12]}; "
        f"{record['date']}; {record['note']}; each row names the machine and date of the run "
        "that measured it. Nordland references (64 x 32: the summer drive, then the winter "
        "drive, then their mirror images) with the size rule off (the search a camera's frames "
        "wait for), seed "
        f"{record['arguments']['seed']}; seconds.",
        "",
        "| references | looked at | pseudo-queries | total | fit | make | extract | score "
        "| search | check | acceptance | load (start, end) | measured on |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in record["timing"].values():
        t, s, m = r["steps_s"], r["sample"], r.get("measured", record)
        steps = " | ".join(
            f"{t[k]:.0f}"
            for k in ("fit_s", "make_s", "extract_s", "score_s", "search_s", "check_s")
        )
        mirrored = f" ({r['mirrored']} mirrored)" if r.get("mirrored") else ""
        lines.append(
            f"| {r['references']}{mirrored} | {s['map']} | {s['pseudo_queries']} | "
            f"**{r['wall_s']:.0f}** "
            f"| {steps} | {t['acceptance_s']:.0f} | {r['load_start'][0]:.1f}, "
            f"{r['load_end'][0]:.1f} | {m['machine']}, {m['date'][:10]} |"
        )
    return "\n".join(lines) + "\n"


def resumed(path: Path, section: str, keep: list[str] | None = None) -> dict[str, Any]:
    """The rows of ``section`` (``routes``, ``timing``) of an earlier run's record at
    ``path`` (those named in ``keep``, or all), each with the provenance of the run that
    measured it (``measured``; a row without one was measured by the record's own run)."""
    old = json.loads(path.read_text())
    keys = ("date", "commit", "code_changed_since_commit", "machine")
    head = {k: old[k] for k in keys if k in old}
    return {
        name: {**row, "measured": row.get("measured", head)}
        for name, row in old.get(section, {}).items()
        if keep is None or name in keep
    }


def main() -> int:
    ap = parser(__doc__)
    add_data(ap)
    add_protocols(ap, choices=tuple(PROTOCOLS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--nordland-frames",
        type=int,
        default=None,
        help="use only the first N Nordland frames (a contiguous part of the route)",
    )
    ap.add_argument("--workers", type=int, default=None, help="extraction processes")
    ap.add_argument(
        "--skip-presets",
        nargs="+",
        default=[],
        choices=ORACLE_PRESETS,
        metavar="PRESET",
        help="leave these presets out of the oracle (recorded per route; e.g. the faithful "
        "presets' KAZE over a whole large map, hours on 2 cores)",
    )
    ap.add_argument(
        "--time",
        type=int,
        nargs="+",
        metavar="N",
        help="measure the choice's time on the first N Nordland references instead (summer, "
        "winter, then their mirror images; the size rule off)",
    )
    add_json(ap, "--out", default=str(DEFAULT_OUT), help="the JSON record (and .md beside it)")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the routes (with --time: the sizes) already in --out, each with the "
        "provenance of its run, and run the rest",
    )
    args = ap.parse_args()
    print(f"Machine: {machine()}", flush=True)
    prov = provenance("default", args=args)
    if args.time:
        rows = time_choice(args.time, args)
        for row in rows.values():
            row["measured"] = {k: prov.get(k) for k in ("date", "commit", "machine")}
        if args.resume and Path(args.out).exists():  # keep the sizes measured before
            rows = {**resumed(Path(args.out), "timing"), **rows}
        timing = {
            **prov,
            "note": "one process, empty cache; each row gives the load at its start and end",
            "timing": dict(sorted(rows.items(), key=lambda kv: int(kv[0]))),
        }
        write_json(args.out, timing)
        text = timing_markdown(timing)
        Path(args.out).with_suffix(".md").write_text(text)
        print(text)
        print(f"wrote {args.out} and {Path(args.out).with_suffix('.md')}")
        return 0
    cache = FeatureCache(args.cache_dir)
    t0 = time.perf_counter()
    routes: dict[str, Any] = {}
    record: dict[str, Any] = {}
    if args.resume and Path(args.out).exists():
        routes = resumed(Path(args.out), "routes", args.protocols)
    for name in args.protocols:
        if name in routes:
            print(f"[{name}] kept from {args.out}", flush=True)
            continue
        started = provenance("default")  # the commit and time the route's code ran from
        routes[name] = {**run_route(name, args, cache), "measured": started}
        record = {
            **prov,
            "note": "2 cores shared with other sessions' jobs: times are indicative only",
            "pool": auto_pool().model_dump(mode="json"),
            "oracle_presets": list(ORACLE_PRESETS),
            "goals": {
                "alpha": ALPHA,
                "oracle_margin": ORACLE_MARGIN,
                "nordland_floor": NORDLAND_FLOOR,
            },
            "routes": routes,
            "complete": len(routes) == len(args.protocols),
            "elapsed_s": time.perf_counter() - t0,
            "load_end": list(os.getloadavg()),
        }
        write_json(args.out, record)  # after every route: a long run keeps what it measured
    if not record:
        print(f"every route asked for is kept from {args.out}: nothing measured, nothing written")
        return 0
    out = Path(args.out)
    text = markdown(record)
    Path(out).with_suffix(".md").write_text(text)
    print(text)
    print(f"wrote {out} and {Path(out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
