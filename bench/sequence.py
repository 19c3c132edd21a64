"""Sequence mode on the shared routes: filter tuned on training parts, reported on test parts.

    python bench/sequence.py [--tune | --per-route] [--out results/sequence.json] [--plots DIR]

Each route is split as ``hmpf-calibrate`` splits it (alternating stretches of 20 frames);
the hierarchy is the default config on Gardens Point and ``calibrated/nordland_handcrafted``
on Nordland (the CNN descriptors fail on the 64x32 thumbnails). The test part's queries are
driven in order as one vehicle along the test part's references (every frame counts, the
first ones included), from random starts, over spliced jumps, at speed ratios 0.5-4 and with
25 % of the frames dropped (:func:`hmpf.evaluation.sequence.sequence_report`).

``--per-route`` instead tunes each route on its own training part (what ``hmpf-calibrate
--sequence`` does for one route). ``--tune`` first searches the filter's settings jointly on
the four training parts (the same score as ``hmpf-calibrate --sequence``, averaged over
routes, so one default serves every route) and the lock threshold for 99 % precision on the
pooled training drives; it prints the settings to make the defaults of
:class:`hmpf.sequence.FilterParams`. Without either the report uses the current defaults.
Plots: recall@1 by frames of history per speed ratio.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hmpf.config import load_config  # noqa: E402
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root  # noqa: E402
from hmpf.evaluation.evaluate import EvalData  # noqa: E402
from hmpf.evaluation.sequence import (  # noqa: E402
    TUNING_GRID,
    format_sequence_report,
    sequence_report,
    sequence_settings,
    tune_sequence,
)
from hmpf.evaluation.study import ScoreBank, split_data  # noqa: E402
from hmpf.features import FeatureCache, default_cache_dir  # noqa: E402
from hmpf.runtime import machine_description  # noqa: E402
from hmpf.sequence import FilterParams, RouteMap  # noqa: E402

ROUTES = {
    **{k: (ref, qry, "default") for k, (ref, qry) in GARDENS_POINT_PROTOCOLS.items()},
    "nordland_s_w": (
        "nordland_64x32/summer",
        "nordland_64x32/winter",
        "calibrated/nordland_handcrafted",
    ),
}


def load_parts(datasets: Path, cache: FeatureCache) -> dict[str, dict[str, Any]]:
    """Per route: the hierarchy's results and ground truth on the training and test parts
    (and each part's references' profile, ``train_profile`` / ``test_profile``, for the
    absolute confidence evidence)."""
    parts: dict[str, dict[str, Any]] = {}
    for name, (ref, qry, cfg_name) in ROUTES.items():
        config = load_config(cfg_name)
        data = EvalData.frames(datasets / ref, datasets / qry, 2)
        parts[name] = {"config": cfg_name}
        for part, d in zip(("train", "test"), split_data(data), strict=True):
            bank = ScoreBank.build(config, d, cache=cache)
            parts[name][part] = (bank.results(config), bank.gt)
            parts[name][f"{part}_profile"] = bank.profile(config)
        print(f"{name}: {len(parts[name]['test'][0])} test queries", flush=True)
    return parts


def tune(parts: dict[str, dict[str, Any]]) -> tuple[FilterParams, dict[str, Any]]:
    """The joint grid search on the training parts (see the module docstring)."""
    training = [
        (results, gt, RouteMap.from_metadata(gt.shape[1]))
        for results, gt in (p["train"] for p in parts.values())
    ]
    names = list(parts)

    def show(row: dict[str, Any]) -> None:
        pairs = zip(names, row["recall"], row["jump_recall"], row["relock_10"], strict=True)
        per_route = ", ".join(f"{n} {r:.3f}/{j:.3f}/{w:.2f}" for n, r, j, w in pairs)
        setting = {k: row[k] for k in TUNING_GRID}
        print(
            f"{setting}: score {row['score']:.4f}, accepted {row['accepted']:.3f} at mass "
            f"{row['lock_mass']:.4f} ({per_route})",
            flush=True,
        )

    return tune_sequence(training, progress=show)


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


def plot(reports: dict[str, dict[str, Any]], out: Path) -> list[Path]:
    """Recall@1 by frames of history, one line per speed ratio, one panel per route."""
    plt = pyplot()
    if plt is None:
        return []
    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(reports), figsize=(4.2 * len(reports), 3.6), sharey=True)
    for ax, (name, rep) in zip(np.atleast_1d(axes), reports.items(), strict=True):
        for ratio, curve in rep["recall_by_history"].items():
            if curve:
                ax.plot(np.arange(1, len(curve) + 1), curve, marker=".", label=f"x{ratio}")
        ax.axhline(rep["single_recall_at_1"], color="grey", ls="--", label="single frame")
        ax.set_title(name)
        ax.set_xlabel("frames since the start of the drive")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("recall@1 (test part)")
    np.atleast_1d(axes)[-1].legend(title="speed ratio", fontsize=8)
    fig.tight_layout()
    path = out / "history_by_speed.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def table(reports: dict[str, dict[str, Any]]) -> str:
    lines = [
        "| route (test part) | single frame | sequence | accepted (precision) "
        "| lock after start (median / p95) | re-lock after jump: within 10 (p95) "
        "| x0.5 / x2 / x4 | 25 % dropped |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in reports.items():
        ls, lj, sp = r["lock_after_start"], r["lock_after_jump"], r["recall_by_speed"]
        lines.append(
            f"| {name} ({r['n_query']}) | {r['single_recall_at_1']:.3f} | "
            f"**{r['recall_at_1']:.3f}** | {r['accepted']['accepted']:.2f} "
            f"({r['accepted']['precision']:.3f}) | {ls['median']:.0f} / {ls['p95']:.0f} | "
            f"{lj['within_10']:.2f} ({lj['p95']:.0f}) | {sp['0.5']:.3f} / {sp['2']:.3f} / "
            f"{sp['4']:.3f} | {r['dropped']['recall_at_1']:.3f} |"
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default=str(dataset_root()))
    ap.add_argument("--cache-dir", default=str(default_cache_dir()))
    ap.add_argument("--tune", action="store_true", help="search the settings first")
    ap.add_argument(
        "--per-route",
        action="store_true",
        help="tune on each route's own training part (as hmpf-calibrate --sequence does)",
    )
    ap.add_argument("--out", default=str(ROOT / "results" / "sequence.json"))
    ap.add_argument("--plots", default=str(ROOT / "docs" / "experiments" / "sequence"))
    args = ap.parse_args()

    t0 = time.perf_counter()
    parts = load_parts(Path(args.datasets), FeatureCache(args.cache_dir))
    params, grid = FilterParams(), {}
    if args.tune:
        params, grid = tune(parts)
        print("chosen settings:", sequence_settings(params))
    reports = {}
    for name, p in parts.items():
        results, gt = p["test"]
        route_params = params
        if args.per_route:
            train_results, train_gt = p["train"]
            routes = RouteMap.from_metadata(train_gt.shape[1])
            route_params, _ = tune_sequence([(train_results, train_gt, routes)])
            print(f"{name}: tuned on its training part: {sequence_settings(route_params)}")
        rep = sequence_report(results, gt, RouteMap.from_metadata(gt.shape[1]), route_params)
        reports[name] = rep
        print(f"\n{name} ({p['config']}), test part:")
        print("\n".join(format_sequence_report(rep)))
    figures = plot(reports, Path(args.plots))
    print(f"\nMachine: {machine_description()}; {time.perf_counter() - t0:.0f} s\n")
    print(table(reports))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(
        json.dumps(
            {
                "machine": machine_description(),
                "params": sequence_settings(params),
                "grid": grid,
                "reports": reports,
                "figures": [str(f) for f in figures],
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
