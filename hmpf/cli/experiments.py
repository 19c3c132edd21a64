"""``hmpf-eval experiments``: the paper's studies on a route's training split.

    hmpf-eval experiments --reference ../shared/datasets/gardens_point/day_right \\
        --query ../shared/datasets/gardens_point/night_right --tolerance 2 --out exp/gp_dr_nr

Writes PNG figures (``fig1``-``fig6``), ``report.md`` and ``experiments.json`` to ``--out``.
``--calibrated FILE`` adds a config written by ``hmpf-calibrate`` to the test-split check;
``--sequence`` adds each checked hierarchy's sequence mode (filter tuned on the training part).
The figures need matplotlib (``pip install 'hmpf[report]'``): checked before any work.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hmpf.cli.args import DEFAULT_POOL, add_sequence_arg, add_split_args, load_banks
from hmpf.errors import HmpfError

PROG = "hmpf-eval experiments"
DESCRIPTION = "Reproduce the paper's studies (Fig. 2-10, Table I) on a training split."


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The command's flags (on its own parser or on ``hmpf-eval``'s subcommand)."""
    add_split_args(p)
    p.add_argument("--out", required=True, help="output folder (figures, report.md, JSON)")
    p.add_argument("--pool", default=DEFAULT_POOL, help="config giving method parameters")
    for flag, default, help_text in (
        (
            "--trio",
            ["gist", "netvlad", "kaze"],
            "methods of the two- and three-tier studies (paper, Nordland)",
        ),
        (
            "--count-trio",
            ["netvlad", "kaze", "olo"],
            "methods of the candidate-count study (paper, Fig. 10)",
        ),
    ):
        p.add_argument(flag, nargs=3, default=default, metavar="METHOD", help=help_text)
    p.add_argument("--k1", type=int, default=20, help="candidates tier 1 passes on")
    p.add_argument("--k2", type=int, default=5, help="candidates tier 2 passes on (3 tiers)")
    p.add_argument("--calibrated", help="a hmpf-calibrate config to check on the test split")
    p.add_argument("--title", default="", help="title of the report and figures")
    add_sequence_arg(p)


def run_experiments(args: argparse.Namespace) -> int:
    """The command's body: check everything cheap first, then score, study and write."""
    from hmpf.config import load_config
    from hmpf.evaluation.experiments import (
        check_pool,
        report_markdown,
        require_matplotlib,
        run_studies,
        write_figures,
    )
    from hmpf.evaluation.study import check_compatible, measure_costs

    if args.k1 < 1 or args.k2 < 1:
        raise HmpfError("--k1 and --k2 must be >= 1")
    require_matplotlib()  # the figures are drawn last: fail before minutes of work
    pool = load_config(args.pool)
    check_pool(pool, args.trio, args.count_trio)  # before any extraction
    calibrated = load_config(args.calibrated) if args.calibrated else None
    if calibrated is not None:
        check_compatible(calibrated, pool)
    train, test = load_banks(args, pool)
    res = run_studies(
        pool,
        train,
        test,
        costs=measure_costs(train),
        trio=args.trio,
        count_trio=args.count_trio,
        k1=args.k1,
        k2=args.k2,
        calibrated=calibrated,
        sequence=args.sequence,
    )
    out = Path(args.out)
    title = args.title or f"{Path(args.reference).name} -> {Path(args.query).name}"
    figures = write_figures(res, out, title)
    md = report_markdown(res, title, figures)
    (out / "report.md").write_text(md)
    (out / "experiments.json").write_text(json.dumps(res, indent=1))
    print(md)
    print(f"wrote {len(figures)} figures, report.md and experiments.json to {out}")
    return 0
