"""``hmpf-eval experiments``: the paper's studies on a route's training split.

    hmpf-eval experiments --reference ../shared/datasets/gardens_point/day_right \\
        --query ../shared/datasets/gardens_point/night_right --tolerance 2 --out exp/gp_dr_nr

Writes PNG figures (``fig1``-``fig6``), ``report.md`` and ``experiments.json`` to ``--out``.
``--calibrated FILE`` adds a config written by ``hmpf-calibrate`` to the test-split check.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hmpf.cli.calibrate import DEFAULT_POOL, add_split_args, load_banks
from hmpf.config import load_config
from hmpf.errors import HmpfError
from hmpf.experiments import check_pool, report_markdown, run_studies, write_figures
from hmpf.study import check_compatible, measure_costs


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="hmpf-eval experiments",
        description="Reproduce the paper's studies (Fig. 2-10, Table I) on a training split.",
    )
    add_split_args(p)
    p.add_argument("--out", required=True, help="output folder (figures, report.md, JSON)")
    p.add_argument("--pool", default=str(DEFAULT_POOL), help="config giving method parameters")
    p.add_argument(
        "--trio",
        nargs=3,
        default=["gist", "netvlad", "kaze"],
        metavar="METHOD",
        help="methods of the two- and three-tier studies (paper, Nordland)",
    )
    p.add_argument(
        "--count-trio",
        nargs=3,
        default=["netvlad", "kaze", "olo"],
        metavar="METHOD",
        help="methods of the candidate-count study (paper, Fig. 10)",
    )
    p.add_argument("--k1", type=int, default=20, help="candidates tier 1 passes on")
    p.add_argument("--k2", type=int, default=5, help="candidates tier 2 passes on (3 tiers)")
    p.add_argument("--calibrated", help="a hmpf-calibrate config to check on the test split")
    p.add_argument("--title", default="", help="title of the report and figures")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.k1 < 1 or args.k2 < 1:
            raise HmpfError("--k1 and --k2 must be >= 1")
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
        )
    except HmpfError as exc:
        print(f"hmpf-eval experiments: error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    title = args.title or f"{Path(args.reference).name} -> {Path(args.query).name}"
    figures = write_figures(res, out, title)
    md = report_markdown(res, title, figures)
    (out / "report.md").write_text(md)
    (out / "experiments.json").write_text(json.dumps(res, indent=1))
    print(md)
    print(f"wrote {len(figures)} figures, report.md and experiments.json to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
