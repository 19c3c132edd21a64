"""``hmpf-calibrate``: choose a hierarchy and its acceptance threshold on a training split.

    hmpf-calibrate --reference ../shared/datasets/gardens_point/day_right \\
        --query ../shared/datasets/gardens_point/night_right --tolerance 2 \\
        --budget-ms 150 --seed 0 --out calibration/gp_dr_nr

The route is split into a training and a test part (``--split blocks``: alternating stretches
of ``--block`` frames; ``halves``: first and second part). The search runs on the training
part only; the test part then checks the winner against its best single method and flat
fusion. Writes ``calibrated.yaml`` (a hierarchy config with ``acceptance.threshold``, ready for
``hmpf-index build --config`` and the service), ``leaderboard.md`` and ``calibration.json``.
Descriptors come through the feature cache, so a second run extracts nothing. With
``--sequence`` the sequence filter's settings and lock threshold are chosen for the winner on
the training part too (written as ``sequence:`` in calibrated.yaml) and its sequence-mode
figures measured on the test part.

The confidence models (:mod:`hmpf.evaluation.acceptance`) are fitted on the training part
too: ``acceptance.model`` / ``model_threshold`` (the probability threshold for
``--target-precision``, chosen on out-of-fold training predictions) and, with
``--sequence``, ``sequence_model`` / ``sequence_threshold``; the z threshold stays as the
fallback. ``--no-model`` writes the z threshold only. The models read absolute evidence
(``ref_z``) and learn from the training part's own out-of-map answers (each stretch of
queries answered with its references removed from the map); the threshold also keeps at most
``1 - target`` of those accepted. ``--no-outside`` leaves them out, for maps that vehicles
never leave: more answers accepted, but a place off the map may be. The test part's ECE,
accepted share and precision of the model and of the z rule are in leaderboard.md and
calibration.json.

The time budget is enforced on a cost model measured on this machine, so the winner may differ
between machines; ``--costs FILE`` (an earlier ``calibration.json``) fixes the cost model, and
with it the choice, on any machine.

``--config NAME_OR_YAML --fit-only`` searches nothing: it fits the acceptance of that
hierarchy (a preset name or a YAML file) as it is, on the same training part and by the same
step as the search's winner (the z threshold, the models, with ``--sequence`` the filter's
settings), measures the test part the same way and writes the same three files:
calibrated.yaml is the given config with its ``acceptance:`` (with ``--sequence`` also its
``sequence:``) replaced, so its digest, and any index built for it, stays the same;
leaderboard.md says it was a fit-only run and gives the digest. ``--methods`` and ``--name``
restrict or rename the searched hierarchy and are errors with ``--fit-only``; the search's
other flags (``--pool``, budget, cost model, search space) are ignored. ``--config``
without ``--fit-only`` is an error too: the search chooses among the methods of ``--pool``.

``--auto --references DIR [--metadata CSV] [--seed N] [--out config.yaml]`` needs no query
at all: it chooses the hierarchy and fits its acceptance from the references alone, on
pseudo-queries made from them (:mod:`hmpf.evaluation.auto`), and prints the candidates and
why the choice was made, without building anything. ``--out`` writes the chosen config (the
YAML ``hmpf-index build --config`` reads) and the record of the choice beside it
(``<out>.reasons.json``: the candidates and their pseudo-query recall, the seed, the sample
sizes, the time taken). ``hmpf-calibrate --auto --help`` lists its options.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hmpf.cli.args import (
    DEFAULT_POOL,
    add_cache_args,
    add_sequence_arg,
    add_split_args,
    cache_from_args,
    load_banks,
)
from hmpf.cli.common import add_version, run
from hmpf.errors import HmpfError

# numpy, OpenCV and the evaluation load inside the command's body (see hmpf.cli.eval).
if TYPE_CHECKING:
    from tqdm import tqdm

    from hmpf.config import HierarchyConfig
    from hmpf.evaluation.study import CostModel, ScoreBank

DEFAULT_NAME = "calibrated"


def _bar_update(bar: tqdm) -> Callable[[int, int], None]:
    """The search's ``progress`` callback driving ``bar`` (its total may grow)."""

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    return update


def write_config(config: HierarchyConfig, path: Path, header: str) -> None:
    """A config as YAML (loadable by :func:`hmpf.config.load_config`) with a comment header."""
    import yaml  # ~0.1 s to import: commands load their modules in run (--help stays instant)

    data = config.model_dump(mode="json", exclude_defaults=False)
    if not data["index"]["faiss"] and not data["index"]["faiss_params"]:
        data.pop("index")
    comment = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    path.write_text(comment + yaml.safe_dump(data, sort_keys=False, width=100))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="hmpf-calibrate",
        description="Search hierarchies on a training split under a time budget; write the "
        "best as a config with its acceptance threshold. With --config NAME --fit-only: no "
        "search, fit the acceptance of that hierarchy as it is.",
    )
    add_version(p)
    p.add_argument(
        "--auto",
        action="store_true",
        help="choose from the references alone, no query needed (hmpf-calibrate --auto --help)",
    )
    add_split_args(p)
    p.add_argument(
        "--pool",
        default=DEFAULT_POOL,
        help="config whose methods the search may use (ignored with --fit-only)",
    )
    p.add_argument("--methods", nargs="*", help="use only these pool methods (not with --fit-only)")
    p.add_argument(
        "--config",
        help="with --fit-only: the hierarchy (a preset name or a YAML file) whose acceptance is "
        "fitted as it is; only with --fit-only (the search chooses among --pool's methods)",
    )
    p.add_argument(
        "--fit-only",
        action="store_true",
        help="no search: fit the acceptance of --config (its z threshold, models and, with "
        "--sequence, the filter's settings) and write it with the config's digest unchanged; "
        "the search's flags (--pool, budget, costs, search space) are then ignored",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--name", help=f"name of the written config (default {DEFAULT_NAME}; not with --fit-only)"
    )
    p.add_argument("--budget-ms", type=float, default=150.0, help="per-query time budget (ms)")
    p.add_argument("--db-size", type=int, help="charge tier 1 for this many references")
    p.add_argument(
        "--costs",
        help="a fixed cost model instead of measuring one: a calibration.json (its 'costs') "
        "or that object alone; the search then picks the same hierarchy on any machine",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--target-precision", type=float, default=0.99)
    p.add_argument("--max-tiers", type=int, default=3, choices=(1, 2, 3))
    p.add_argument("--max-per-tier", type=int, default=2, choices=(1, 2, 3))
    p.add_argument("--k1", type=int, nargs="+", default=[5, 10, 20], help="tier-1 counts")
    p.add_argument("--k2", type=int, nargs="+", default=[2, 3, 5], help="tier-2 counts")
    p.add_argument("--samples", type=int, default=1500, help="3-tier structures drawn")
    p.add_argument("--refine", type=int, default=25, help="structures searched in full")
    p.add_argument("--top", type=int, default=20, help="leaderboard length")
    add_sequence_arg(p)
    p.add_argument(
        "--no-model",
        action="store_true",
        help="do not fit the confidence models (acceptance by the z threshold only)",
    )
    p.add_argument(
        "--no-outside",
        action="store_true",
        help="fit the models without the training part's out-of-map answers (for maps that "
        "vehicles never leave)",
    )
    return p


def load_costs(path: str) -> CostModel:
    """The cost model in a JSON file: a calibration report (its ``costs``) or that object."""
    from hmpf.evaluation.study import CostModel

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise HmpfError(f"cannot read the cost model {path}: {exc}") from exc
    return CostModel.from_dict(data.get("costs", data) if isinstance(data, dict) else data)


def _pool_and_methods(args: argparse.Namespace) -> tuple[HierarchyConfig, tuple[str, ...]]:
    """The pool (restricted to ``--methods``) and the methods the search may use."""
    from hmpf.config import load_config
    from hmpf.evaluation.study import derive_config

    pool = load_config(args.pool)
    methods = tuple(dict.fromkeys(args.methods or pool.method_ids))  # once each
    unknown = sorted(set(methods) - set(pool.method_ids))
    if unknown:
        raise HmpfError(
            f"--methods not in the pool {args.pool}: {', '.join(unknown)} "
            f"(pool: {', '.join(pool.method_ids)})"
        )
    if set(methods) != set(pool.method_ids):
        # Score only the methods the search may use: a bank holds every pool method's
        # full score matrix, and the unused ones (KAZE, OLO) cost the most to score.
        pool = derive_config(
            pool, [(methods, 1)], None, name=pool.name, description=pool.description
        )
    return pool, methods


def mode_error(args: argparse.Namespace) -> str | None:
    """Why the mode flags do not go together (``--fit-only`` and ``--config``), or None."""
    if args.fit_only and args.config is None:
        return "--fit-only needs --config (the hierarchy whose acceptance is fitted)"
    if args.config is not None and not args.fit_only:
        return (
            "--config is only read with --fit-only (fit that hierarchy's acceptance as it is); "
            "the search chooses among the methods of --pool"
        )
    if args.fit_only:
        pairs = (("--methods", args.methods), ("--name", args.name))
        given = [flag for flag, value in pairs if value is not None]
        if given:
            return (
                f"{', '.join(given)} not with --fit-only: it keeps --config as it is "
                "(its methods and name are part of its digest)"
            )
    return None


def _check_args(args: argparse.Namespace) -> None:
    if not 0 < args.target_precision <= 1:
        raise HmpfError("--target-precision must be in (0, 1]")
    if args.budget_ms <= 0:
        raise HmpfError("--budget-ms must be positive")
    if min(args.k1 + args.k2) < 1:
        raise HmpfError("candidate counts must be >= 1")


def _write(args: argparse.Namespace, config: HierarchyConfig, report: dict[str, Any]) -> None:
    """calibrated.yaml, leaderboard.md and calibration.json in ``--out``; the board printed."""
    from hmpf.evaluation.calibrate import leaderboard_markdown

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_config(config, out / "calibrated.yaml", _header(args, report))
    md = leaderboard_markdown(report)
    (out / "leaderboard.md").write_text(md)
    (out / "calibration.json").write_text(json.dumps(report, indent=1))
    print(md)
    print(f"wrote {out / 'calibrated.yaml'}, {out / 'leaderboard.md'}, {out / 'calibration.json'}")


def _header(args: argparse.Namespace, report: dict[str, Any]) -> str:
    """calibrated.yaml's comment: how it was written, on which route, its training figures."""
    route = (
        f"Route: {args.reference} -> {args.query}, {args.split} split, "
        f"{report['protocol']['ground_truth']}."
    )
    tr = report["train"]
    if report.get("mode") == "fit-only":
        return (
            f"Written by hmpf-calibrate --fit-only (seed {args.seed}): the acceptance of "
            f"{args.config}, no search.\n{route}\n"
            f"Training recall@1 {tr['recall_at_1']:.3f}; config digest {report['digest']}."
        )
    win = tr["winner"]
    return (
        f"Written by hmpf-calibrate (seed {args.seed}, budget {args.budget_ms:g} ms/query).\n"
        f"{route}\n"
        f"Training recall@1 {win['recall_at_1']:.3f}, modelled {win['model_ms']:.1f} ms/query."
    )


def _protocol(args: argparse.Namespace, train: ScoreBank) -> dict[str, Any]:
    """The report's ``protocol``: the route, its ground truth and split, the pool or config."""
    source = {"config": args.config} if args.fit_only else {"pool": args.pool}
    return {
        "reference": args.reference,
        "query": args.query,
        "ground_truth": train.data.ground_truth,
        "split": args.split,
        "block": args.block,
        **source,
    }


def run_fit_only(args: argparse.Namespace) -> int:
    """``--fit-only``: score the split for --config, fit its acceptance, write."""
    from hmpf.config import load_config
    from hmpf.evaluation.calibrate import fit_only

    _check_args(args)
    given = load_config(args.config)
    train, test = load_banks(args, given)
    config, report = fit_only(given, train, test, **_acceptance_args(args))
    report["protocol"] = _protocol(args, train)
    _write(args, config, report)
    return 0


def _acceptance_args(args: argparse.Namespace) -> dict[str, Any]:
    """What the search and ``--fit-only`` both pass to the acceptance fit."""
    return {
        "seed": args.seed,
        "target_precision": args.target_precision,
        "sequence": args.sequence,
        "model": not args.no_model,
        "outside": not args.no_outside,
    }


def run_calibrate(args: argparse.Namespace) -> int:
    """The command's body: check the flags, score the split, search (or, ``--fit-only``,
    fit the given config), write."""
    from tqdm import tqdm  # a command: its modules load in run, --help stays instant

    from hmpf.evaluation.calibrate import SearchSpace, calibrate

    if args.fit_only:
        return run_fit_only(args)
    _check_args(args)
    costs = load_costs(args.costs) if args.costs else None
    pool, methods = _pool_and_methods(args)
    train, test = load_banks(args, pool)
    space = SearchSpace(
        methods,
        max_tiers=args.max_tiers,
        max_per_tier=args.max_per_tier,
        k1=tuple(args.k1),
        k2=tuple(args.k2),
        samples=args.samples,
        refine=args.refine,
    )
    bar = tqdm(desc="search", unit="hierarchy", disable=True if args.quiet else None)
    with bar:
        config, report = calibrate(
            pool,
            train,
            test,
            space,
            budget_ms=args.budget_ms,
            db_size=args.db_size,
            name=args.name or DEFAULT_NAME,
            top=args.top,
            progress=_bar_update(bar),
            costs=costs,
            **_acceptance_args(args),
        )
    report["protocol"] = _protocol(args, train)
    _write(args, config, report)
    return 0


# -- --auto: the choice from the references alone ---------------------------------------------


def build_auto_parser() -> argparse.ArgumentParser:
    """``hmpf-calibrate --auto``'s own options (no query, no split)."""
    p = argparse.ArgumentParser(
        prog="hmpf-calibrate --auto",
        description="Choose a hierarchy and fit its acceptance from the references alone, on "
        "pseudo-queries made from them; print the candidates and why, build nothing.",
    )
    add_version(p)
    p.add_argument("--auto", action="store_true", help="this mode (required)")
    p.add_argument("--references", required=True, help="folder of reference images")
    p.add_argument(
        "--metadata",
        help="CSV: name[,lat,lon,heading,timestamp,sequence] (the indexer's): route order, and "
        "with GPS what is right for a pseudo-query",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--out",
        help="write the chosen config here (YAML) and the record of the choice beside it "
        "(<out>.reasons.json)",
    )
    p.add_argument("--name", default="auto", help="name of a config the search found")
    p.add_argument(
        "--pool", help="config whose methods the search may use (default: the automatic pool)"
    )
    p.add_argument("--budget-ms", type=float, default=150.0, help="per-query time budget (ms)")
    p.add_argument(
        "--costs",
        help="a fixed cost model (a calibration.json or its 'costs'); default: the nominal "
        "figures of the automatic pool's methods",
    )
    p.add_argument("--max-references", type=int, default=1000, help="references looked at")
    p.add_argument("--max-queries", type=int, default=400, help="pseudo-queries made")
    p.add_argument(
        "--tolerance", type=int, default=2, help="right: within +-T positions along the route"
    )
    p.add_argument(
        "--radius-m", type=float, default=25.0, help="right, with GPS: within this many metres"
    )
    p.add_argument(
        "--alpha",
        type=float,
        default=0.05,
        help="sign-test level for leaving the default on held-out pseudo-queries",
    )
    p.add_argument("--target-precision", type=float, default=0.99)
    p.add_argument("--no-model", action="store_true", help="z threshold only, no models")
    p.add_argument("--no-outside", action="store_true", help="models without out-of-map answers")
    add_cache_args(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def _auto_check(args: argparse.Namespace) -> None:
    if not 0 < args.target_precision <= 1:
        raise HmpfError("--target-precision must be in (0, 1]")
    if args.budget_ms <= 0:
        raise HmpfError("--budget-ms must be positive")
    if args.max_references < 8 or args.max_queries < 2:
        raise HmpfError("--max-references must be >= 8 and --max-queries >= 2")
    if not 0 < args.alpha < 1:
        raise HmpfError("--alpha must be in (0, 1)")


def run_auto(args: argparse.Namespace) -> int:
    """``--auto``: plan, make and score the pseudo-queries, search, check, fit, print (and
    with ``--out`` write)."""
    from tqdm import tqdm  # a command: its modules load in run, --help stays instant

    from hmpf.config import load_config
    from hmpf.datasets import list_images
    from hmpf.evaluation.auto import choose_config
    from hmpf.evaluation.pseudo import read_metadata_csv

    _auto_check(args)
    refs = list_images(args.references)
    if not refs:
        raise HmpfError(f"no images in {args.references}")
    metadata = read_metadata_csv(args.metadata, [r.name for r in refs]) if args.metadata else None
    bar = tqdm(desc="search", unit="hierarchy", disable=True if args.quiet else None)
    with bar:
        config, reasons = choose_config(
            refs,
            metadata,
            seed=args.seed,
            cache=cache_from_args(args),
            pool=load_config(args.pool) if args.pool else None,
            budget_ms=args.budget_ms,
            costs=load_costs(args.costs) if args.costs else None,
            alpha=args.alpha,
            max_references=args.max_references,
            max_queries=args.max_queries,
            tolerance=args.tolerance,
            radius_m=args.radius_m,
            target_precision=args.target_precision,
            model=not args.no_model,
            outside=not args.no_outside,
            name=args.name,
            workers=args.workers,
            progress=not args.quiet,
            search_progress=_bar_update(bar),
        )
    reasons["protocol"] = {"references": args.references, "metadata": args.metadata}
    text = auto_markdown(reasons)
    print(text)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_config(config, out, _auto_header(args, reasons))
        side = out.with_name(out.name + ".reasons.json")
        side.write_text(json.dumps(reasons, indent=1))
        print(f"wrote {out} and {side}")
    return 0


def _auto_header(args: argparse.Namespace, reasons: dict[str, Any]) -> str:
    ch, sample = reasons["chosen"], reasons["sample"]
    if "rule" in reasons:  # thumbnails: no pseudo-query was made
        return (
            f"Written by hmpf-calibrate --auto from the references in {args.references} alone.\n"
            f"Chosen: {ch['hierarchy']} (digest {reasons['digest'][:16]}): {ch['why']}.\n"
            f"The record of the choice: {Path(args.out).name}.reasons.json."
        )
    return (
        f"Written by hmpf-calibrate --auto (seed {args.seed}) from the references in "
        f"{args.references} alone.\n"
        f"Chosen: {ch['hierarchy']} (digest {reasons['digest'][:16]}): {ch['why']}.\n"
        f"{sample['pseudo_queries']} pseudo-queries from {sample['sources']} of "
        f"{sample['references']} references; the record of the choice: "
        f"{Path(args.out).name}.reasons.json."
    )


def auto_markdown(reasons: dict[str, Any]) -> str:
    """The record of an automatic choice as Markdown: the sample, the candidates, the
    decision and the time taken."""
    s, ch, t = reasons["sample"], reasons["chosen"], reasons["time_s"]
    if "rule" in reasons:  # thumbnails: no pseudo-query was made
        return (
            f"# Automatic choice from the references ({reasons['machine']})\n\n"
            f"{s['references']} references ({s['sized']} of them sized).\n\n"
            f"Chosen: **{ch['hierarchy']}** (config digest {reasons['digest'][:16]}): "
            f"{ch['why']}.\n\nTime: {t['total_s']:.1f} s.\n"
        )
    lines = [
        f"# Automatic choice from the references ({reasons['machine']})",
        "",
        f"Seed {reasons['seed']}; {s['map']} of {s['references']} references looked at "
        f"({s['fit']} fit the methods); {s['pseudo_queries']} pseudo-queries from "
        f"{s['sources']} of them ({s['search']} rank the hierarchies, {s['check']} held out "
        f"check the choice); right: {s['truth']}. Pool {reasons['pool']}, budget "
        f"{reasons['budget_ms']} ms per query ({reasons['costs_source']} costs), "
        f"{reasons['evaluated']} hierarchies searched.",
        "",
        "| hierarchy | pseudo recall@1 (search) | pseudo recall@1 (held out) | modelled ms |",
        "|---|---|---|---|",
    ]
    for c in reasons["candidates"]:
        check = "" if c["check_recall_at_1"] is None else f"{c['check_recall_at_1']:.3f}"
        lines.append(
            f"| {c['hierarchy']} | {c['search_recall_at_1']:.3f} | {check} | {c['model_ms']:.1f} |"
        )
    lines += [
        "",
        f"Chosen: **{ch['hierarchy']}** (config digest {reasons['digest'][:16]}): {ch['why']}.",
        "",
        f"Time: {t['total_s']:.0f} s (fit {t['fit_s']:.0f}, pseudo-queries {t['make_s']:.0f}, "
        f"extraction {t['extract_s']:.0f}, scoring {t['score_s']:.0f}, search "
        f"{t['search_s']:.0f}, check {t['check_s']:.0f}, acceptance {t['acceptance_s']:.0f}).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--auto" in argv:
        auto_args = build_auto_parser().parse_args(argv)
        return run("hmpf-calibrate", lambda: run_auto(auto_args))
    parser = build_parser()
    args = parser.parse_args(argv)
    error = mode_error(args)
    if error is not None:
        parser.error(error)  # usage, the message and exit 2, as argparse's own errors
    return run("hmpf-calibrate", lambda: run_calibrate(args))


if __name__ == "__main__":
    sys.exit(main())
