"""The paper's studies, calibration and the headline table on the Gardens Point protocols.

    python -m bench.paper_experiments [--protocols gp_dr_nr ...] [--budget-ms 150] [--seed 0]

Per protocol (reference -> query, +-2 frames, ``blocks`` split: alternating stretches of 20
frames, 100 training and 100 test frames): ``hmpf-calibrate``'s search on the training part
(written to ``configs/calibrated/<protocol>.yaml``), the six studies with their figures
(``docs/experiments/<protocol>/``), then on the test part the calibrated hierarchy against its
best single method, flat fusion of its methods, the paper presets and the default config,
each with its time per query measured end to end (one compute thread, median of 10 queries).
Writes ``docs/experiments/README.md`` (the headline table and links). Descriptors come from
the feature cache; a cold run extracts every method for 600 images first.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from bench.harness import ROOT, add_data, add_protocols, parser, protocol_data, write_json
from hmpf.cli.calibrate import write_config
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS as PROTOCOLS
from hmpf.evaluation.calibrate import SearchSpace, calibrate, compare_on, leaderboard_markdown
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.experiments import report_markdown, run_studies, write_figures
from hmpf.evaluation.study import ScoreBank, measure_query_ms, split_data
from hmpf.features import FeatureCache

PRESETS = ("paper-nordland", "paper-berlin", "default")


def headline_row(
    proto: str, title: str, rep: dict[str, Any], test_data: EvalData, cache: FeatureCache
) -> dict[str, Any]:
    """The headline table's row of a protocol: the calibrated hierarchy on the test part,
    its best single method, flat fusion, and the paper presets and the default."""
    win, te = rep["train"]["winner"], rep["test"]
    row = {
        "protocol": proto,
        "title": title,
        "calibrated": win["hierarchy"],
        "calibrated_test": te["recall_at_1"],
        "calibrated_ms": te["measured_ms"]["total_ms"],
        "best_single": te["best_single"],
        "best_single_test": te["best_single_recall_at_1"],
        "flat_test": te["flat_recall_at_1"],
        "vs_best_single": te["vs_best_single"],
        "vs_flat": te["vs_flat"],
        "threshold": rep["train"]["acceptance"]["threshold"],
        "train_acceptance": rep["train"]["acceptance"],
        "test_acceptance": te["acceptance"],
        "presets": {},
    }
    for name in PRESETS:
        preset = load_config(ROOT / "configs" / f"{name}.yaml")
        bank = ScoreBank.build(preset, test_data, cache=cache)
        cmp = compare_on(bank, preset, preset)
        row["presets"][name] = {
            "test": cmp["recall_at_1"],
            "ms": measure_query_ms(preset, bank)["total_ms"],
        }
    return row


def run_protocol(
    proto: str, pool: HierarchyConfig, cache: FeatureCache, args: argparse.Namespace
) -> dict[str, Any]:
    """Calibrate on ``proto``'s training part, run the studies, write the config, the
    leaderboard, the reports and figures; returns its headline row."""
    r, q = PROTOCOLS[proto]
    data = protocol_data(proto, args.datasets)
    train_data, test_data = split_data(data, scheme=args.split)
    train = ScoreBank.build(pool, train_data, cache=cache)
    test = ScoreBank.build(pool, test_data, cache=cache)
    space = SearchSpace(tuple(pool.method_ids))
    config, rep = calibrate(
        pool, train, test, space, budget_ms=args.budget_ms, seed=args.seed,
        name=f"calibrated-{proto}",
    )  # fmt: skip
    rep["protocol"] = {
        "reference": r,
        "query": q,
        "split": args.split,
        "ground_truth": "frames +-2",
    }
    out = Path(args.out) / proto
    out.mkdir(parents=True, exist_ok=True)
    win = rep["train"]["winner"]
    write_config(
        config,
        Path(args.configs_out) / f"{proto}.yaml",
        f"Calibrated by bench/paper_experiments.py (hmpf-calibrate's search; seed {args.seed}, "
        f"budget {args.budget_ms:g} ms/query)\non Gardens Point {r} -> {q}, training part of "
        f"the {args.split} split, frames +-2.\nTraining recall@1 {win['recall_at_1']:.3f}; "
        f"test recall@1 {rep['test']['recall_at_1']:.3f} (docs/experiments/{proto}/).",
    )
    (out / "leaderboard.md").write_text(leaderboard_markdown(rep))
    write_json(out / "calibration.json", rep)
    title = f"Gardens Point {Path(r).name} -> {Path(q).name}"
    res = run_studies(pool, train, test, costs=None, calibrated=config)
    figures = write_figures(res, out, title)
    (out / "report.md").write_text(
        report_markdown(res, title, figures)
        + "\nCalibration leaderboard: [leaderboard.md](leaderboard.md).\n"
    )
    write_json(out / "experiments.json", res)
    return headline_row(proto, title, rep, test_data, cache)


def main() -> int:
    ap = parser(__doc__)
    add_protocols(ap, choices=PROTOCOLS)
    add_data(ap)
    ap.add_argument("--budget-ms", type=float, default=150.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--split", default="blocks", choices=("blocks", "halves"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "experiments"))
    ap.add_argument("--configs-out", default=str(ROOT / "configs" / "calibrated"))
    args = ap.parse_args()
    cache = FeatureCache(args.cache_dir)
    pool = load_config(ROOT / "configs" / "calibration-pool.yaml")
    Path(args.configs_out).mkdir(parents=True, exist_ok=True)
    headline = []
    for proto in args.protocols:
        t0 = time.perf_counter()
        row = run_protocol(proto, pool, cache, args)
        headline.append(row)
        print(json.dumps({k: v for k, v in row.items() if "acceptance" not in k}, indent=1))
        print(f"{proto}: {time.perf_counter() - t0:.0f} s", flush=True)
    write_json(Path(args.out) / "headline.json", headline)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
