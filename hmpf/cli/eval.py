"""``hmpf-eval``: evaluate a hierarchy on a reference / query image pair of folders.

    hmpf-eval --config handcrafted \\
        --reference ../shared/datasets/gardens_point/day_right \\
        --query ../shared/datasets/gardens_point/night_right --tolerance 2 --json out.json

``hmpf-eval experiments ...`` runs the paper's studies on a train/test split instead
(:mod:`hmpf.cli.experiments`); without a subcommand ``hmpf-eval`` evaluates one hierarchy.

With ``--index DIR`` the references come from a built index (``hmpf-index build``) and the
queries run through the same code as the service (``--config`` and ``--reference`` are then
optional; a given ``--config`` must match the index's).

With ``--sequence`` the queries are also driven in order as one vehicle through the sequence
filter (:mod:`hmpf.evaluation.sequence`); the config's ``sequence:`` settings apply.

The config's acceptance is applied to every answer (report ``acceptance``): with a
confidence model (``acceptance.model``, written by ``hmpf-calibrate``) each answer gets
``p_correct`` and is accepted when ``p_correct >= model_threshold``; without one
``p_correct`` is null and the Combined z rule decides (sequence mode: the sequence model, or
the posterior mass >= the filter's lock threshold). The report says which rule decided, and
its accepted share, precision and (for a model) expected calibration error.

Ground truth: frame alignment (``--tolerance T``, the default form), ``--gt-csv FILE``
(query,reference[,tolerance] rows) or ``--gps-csv FILE --radius-m R`` (role,name,lat,lon).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hmpf.cli import experiments
from hmpf.cli.args import (
    add_cache_args,
    add_ground_truth_args,
    add_sequence_arg,
    cache_from_args,
    ground_truth_from_args,
)
from hmpf.cli.common import add_version, run

# numpy, OpenCV and the evaluation load inside the command's body (`run`), so that --help and
# --version are instant and Ctrl-C while they load is one line and exit 130 too.
if TYPE_CHECKING:
    pass

PROG = "hmpf-eval"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        usage="%(prog)s [options] --config YAML --reference DIR --query DIR\n"
        "       %(prog)s [options] --index DIR --query DIR\n"
        "       %(prog)s experiments [options] --reference DIR --query DIR --out DIR",
        description="Evaluate an HMPF hierarchy (and every method alone) on real images. "
        "Without a command: evaluate --config on --reference and --query (or --index).",
    )
    add_version(p)
    p.add_argument("--config", help="a preset name (e.g. handcrafted) or a hierarchy YAML file")
    p.add_argument("--reference", help="folder of reference (database) images")
    p.add_argument("--index", help="evaluate against this built index instead of --reference")
    p.add_argument("--query", help="folder of query images (required)")
    add_ground_truth_args(p)
    p.add_argument("--json", help="write the full report as JSON to this file")
    add_cache_args(p)
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
    add_sequence_arg(p)
    p.add_argument(
        "--foreign",
        metavar="DIR",
        help="with --sequence: frames of places the map does not hold (in driving order); "
        "drives then leave the map and come back (the off-map state's figures)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    commands = p.add_subparsers(dest="command", title="commands", metavar="COMMAND")
    sub = commands.add_parser(
        "experiments",
        prog=experiments.PROG,
        help=experiments.DESCRIPTION,
        description=experiments.DESCRIPTION,
    )
    add_version(sub)
    experiments.add_arguments(sub)
    return p


def _evaluate_index(args: argparse.Namespace) -> dict[str, Any]:
    from hmpf.config import load_config
    from hmpf.datasets import list_images
    from hmpf.evaluation.evaluate import evaluate_index
    from hmpf.index.reader import IndexReader

    expected = load_config(args.config) if args.config else None
    with IndexReader(args.index, expected_config=expected) as reader:
        qrys = list_images(args.query)[: args.limit]
        # Ground truth is on places (a fleet experience is not a place of its own).
        gt, desc = ground_truth_from_args(args, qrys, reader.place_names)
        return evaluate_index(
            reader,
            qrys,
            gt,
            desc,
            cache=cache_from_args(args),
            workers=args.workers,
            progress=not args.quiet,
            sequence=args.sequence,
        )


def _evaluate_route(args: argparse.Namespace) -> dict[str, Any]:
    from hmpf.config import load_config
    from hmpf.datasets import list_images
    from hmpf.evaluation.evaluate import EvalData, evaluate

    config = load_config(args.config)
    refs = list_images(args.reference)[: args.limit]
    qrys = list_images(args.query)[: args.limit]
    gt, desc = ground_truth_from_args(args, qrys, [r.name for r in refs])
    foreign = list_images(args.foreign) if args.foreign else []
    return evaluate(
        config,
        EvalData(refs, qrys, gt, desc),
        cache=cache_from_args(args),
        workers=args.workers,
        skip_curves=args.skip_curves,
        progress=not args.quiet,
        sequence=args.sequence,
        foreign=foreign,
    )


def run_eval(args: argparse.Namespace) -> int:
    """The command's body without a subcommand: evaluate, print, write the JSON."""
    from hmpf.evaluation.evaluate import format_index_report, format_report

    if args.index is not None:
        report = _evaluate_index(args)
        print(format_index_report(report))
    else:
        report = _evaluate_route(args)
        print(format_report(report))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "experiments":
        return run(experiments.PROG, lambda: experiments.run_experiments(args))
    if args.query is None:
        parser.error("--query is required")
    if args.foreign and (not args.sequence or args.index is not None):
        parser.error("--foreign needs --sequence and --reference (not --index)")
    if args.index is None and (args.config is None or args.reference is None):
        parser.error("--config and --reference are required (or --index DIR)")
    return run(PROG, lambda: run_eval(args))


if __name__ == "__main__":
    sys.exit(main())
