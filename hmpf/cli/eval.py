"""``hmpf-eval``: evaluate a hierarchy on a reference / query image pair of folders.

    hmpf-eval --config configs/handcrafted.yaml \\
        --reference ../shared/datasets/gardens_point/day_right \\
        --query ../shared/datasets/gardens_point/night_right --tolerance 2 --json out.json

``hmpf-eval experiments ...`` runs the paper's studies on a train/test split instead
(:mod:`hmpf.cli.experiments`).

With ``--index DIR`` the references come from a built index (``hmpf-index build``) and the
queries run through the same code as the service (``--config`` and ``--reference`` are then
optional; a given ``--config`` must match the index's).

Ground truth: frame alignment (``--tolerance T``, the default form), ``--gt-csv FILE``
(query,reference[,tolerance] rows) or ``--gps-csv FILE --radius-m R`` (role,name,lat,lon).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from hmpf.config import load_config
from hmpf.datasets import frame_ground_truth, gps_ground_truth, list_images, pairs_ground_truth
from hmpf.errors import HmpfError
from hmpf.evaluate import EvalData, evaluate, format_report
from hmpf.features import FeatureCache, default_cache_dir


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="hmpf-eval",
        description="Evaluate an HMPF hierarchy (and every method alone) on real images.",
    )
    p.add_argument("--config", help="hierarchy YAML (e.g. configs/handcrafted.yaml)")
    p.add_argument("--reference", help="folder of reference (database) images")
    p.add_argument("--index", help="evaluate against this built index instead of --reference")
    p.add_argument("--query", required=True, help="folder of query images")
    add_ground_truth_args(p)
    p.add_argument("--json", help="write the full report as JSON to this file")
    p.add_argument("--cache-dir", help=f"descriptor cache (default {default_cache_dir()})")
    p.add_argument("--no-cache", action="store_true", help="always extract, never cache")
    p.add_argument("--workers", type=int, default=None, help="extraction processes (default: CPUs)")
    p.add_argument(
        "--limit",
        type=int,
        default=None,
        help="use only the first N images of each folder (quick runs)",
    )
    p.add_argument(
        "--skip-curves",
        nargs="*",
        default=[],
        metavar="METHOD",
        help="methods whose whole-database curve is not computed",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def add_ground_truth_args(p: argparse.ArgumentParser) -> None:
    """The ground-truth flags shared by hmpf-eval, its experiments and hmpf-calibrate."""
    gt = p.add_mutually_exclusive_group()
    gt.add_argument("--tolerance", type=int, help="frame-aligned ground truth: |q - r| <= T")
    gt.add_argument("--gt-csv", help="CSV of query,reference[,tolerance] pairs")
    gt.add_argument("--gps-csv", help="CSV role,name,lat,lon; needs --radius-m")
    p.add_argument("--radius-m", type=float, help="GPS ground-truth radius in metres")


def ground_truth_from_args(
    args: argparse.Namespace, qrys: list[Path], ref_names: list[str]
) -> tuple[np.ndarray, str]:
    """(gt matrix, description) from the ground-truth flags."""
    if args.gt_csv:
        gt = pairs_ground_truth(args.gt_csv, [q.name for q in qrys], ref_names)
        return gt, f"pairs from {args.gt_csv}"
    if args.gps_csv:
        if args.radius_m is None:
            raise HmpfError("--gps-csv needs --radius-m")
        gt = gps_ground_truth(args.gps_csv, [q.name for q in qrys], ref_names, args.radius_m)
        return gt, f"GPS within {args.radius_m:g} m"
    tol = 2 if args.tolerance is None else args.tolerance
    return frame_ground_truth(len(qrys), len(ref_names), tol), f"frames +-{tol}"


def _main_index(args: argparse.Namespace) -> int:
    from hmpf.index.evaluate import evaluate_index, format_index_report
    from hmpf.index.reader import IndexReader

    expected = load_config(args.config) if args.config else None
    with IndexReader(args.index, expected_config=expected) as reader:
        qrys = list_images(args.query)[: args.limit]
        gt, desc = ground_truth_from_args(args, qrys, reader.refs.names)
        cache = None if args.no_cache else FeatureCache(args.cache_dir or default_cache_dir())
        report = evaluate_index(
            reader, qrys, gt, desc, cache=cache, workers=args.workers, progress=not args.quiet
        )
    print(format_index_report(report))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["experiments"]:
        from hmpf.cli.experiments import main as experiments_main

        return experiments_main(argv[1:])
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.index is None and (args.config is None or args.reference is None):
        parser.error("--config and --reference are required (or --index DIR)")
    if args.index is not None:
        try:
            return _main_index(args)
        except HmpfError as exc:
            print(f"hmpf-eval: error: {exc}", file=sys.stderr)
            return 2
    try:
        config = load_config(args.config)
        refs = list_images(args.reference)[: args.limit]
        qrys = list_images(args.query)[: args.limit]
        gt, desc = ground_truth_from_args(args, qrys, [r.name for r in refs])
        cache = None if args.no_cache else FeatureCache(args.cache_dir or default_cache_dir())
        report = evaluate(
            config,
            EvalData(refs, qrys, gt, desc),
            cache=cache,
            workers=args.workers,
            skip_curves=args.skip_curves,
            progress=not args.quiet,
        )
    except HmpfError as exc:
        print(f"hmpf-eval: error: {exc}", file=sys.stderr)
        return 2
    print(format_report(report))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
