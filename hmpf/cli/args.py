"""The argument helpers the evaluation commands share (``hmpf-eval``, ``hmpf-eval
experiments``, ``hmpf-calibrate``): the data, ground-truth, split, cache and sequence flags,
and what they name (the ground truth, the descriptor cache, the score banks).

Each command module imports this one; none imports another command's module for them.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from hmpf.errors import HmpfError
from hmpf.evaluation import SPLITS
from hmpf.runtime import default_cache_dir

# numpy, OpenCV and the evaluation load inside the functions that need them (called from a
# command's body, ``run``), so that --help and --version are instant and Ctrl-C while they
# load is one line and exit 130 too (tests/hmpf/test_cli_common.py).
if TYPE_CHECKING:
    import numpy as np

    from hmpf.config import HierarchyConfig
    from hmpf.evaluation.study import ScoreBank
    from hmpf.features import FeatureCache

__all__ = [
    "DEFAULT_POOL",
    "add_cache_args",
    "add_ground_truth_args",
    "add_sequence_arg",
    "add_split_args",
    "cache_from_args",
    "ground_truth_from_args",
    "load_banks",
]

DEFAULT_POOL = "calibration-pool"  # a preset name (hmpf/presets/calibration-pool.yaml)


def add_cache_args(p: argparse.ArgumentParser) -> None:
    """The descriptor-cache and extraction flags shared by hmpf-eval and hmpf-calibrate."""
    p.add_argument("--cache-dir", help=f"descriptor cache (default {default_cache_dir()})")
    p.add_argument("--no-cache", action="store_true", help="always extract, never cache")
    p.add_argument("--workers", type=int, default=None, help="extraction processes (default: CPUs)")


def add_sequence_arg(p: argparse.ArgumentParser) -> None:
    """``--sequence``, shared by hmpf-eval, its experiments and hmpf-calibrate."""
    p.add_argument(
        "--sequence",
        action="store_true",
        help="also drive the queries in order as one vehicle through the sequence filter "
        "(frames to lock on after a start and a jump, recall by speed, accepted answers)",
    )


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
    from hmpf.datasets import frame_ground_truth, gps_ground_truth, pairs_ground_truth

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


def cache_from_args(args: argparse.Namespace) -> FeatureCache | None:
    """The descriptor cache the flags name (None with ``--no-cache``)."""
    from hmpf.features import FeatureCache

    return None if args.no_cache else FeatureCache(args.cache_dir or default_cache_dir())


def add_split_args(p: argparse.ArgumentParser) -> None:
    """Data, split and cache flags shared with ``hmpf-eval experiments``."""
    p.add_argument("--reference", required=True, help="folder of reference images")
    p.add_argument("--query", required=True, help="folder of query images")
    add_ground_truth_args(p)
    p.add_argument("--split", choices=SPLITS, default="blocks", help="train/test split")
    p.add_argument("--block", type=int, default=20, help="frames per stretch (blocks split)")
    p.add_argument("--train-fraction", type=float, default=0.5, help="halves split: train share")
    add_cache_args(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def load_banks(args: argparse.Namespace, pool: HierarchyConfig) -> tuple[ScoreBank, ScoreBank]:
    """Split the route given by the flags and score the pool on both parts."""
    from hmpf.datasets import list_images
    from hmpf.evaluation.data import EvalData
    from hmpf.evaluation.study import ScoreBank, split_data

    refs = list_images(args.reference)
    qrys = list_images(args.query)
    gt, desc = ground_truth_from_args(args, qrys, [r.name for r in refs])
    parts = split_data(
        EvalData(refs, qrys, gt, desc), args.train_fraction, scheme=args.split, block=args.block
    )
    cache = cache_from_args(args)
    train, test = (
        ScoreBank.build(pool, part, cache=cache, workers=args.workers, progress=not args.quiet)
        for part in parts
    )
    return train, test
