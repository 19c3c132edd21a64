"""``hmpf-index``: build, extend and maintain versioned reference indexes.

    hmpf-index build --config handcrafted --images refs/ --index maps/campus
    hmpf-index build --config auto --images refs/ --index maps/campus [--metadata route.csv]
    hmpf-index add --index maps/campus --images new_refs/ [--metadata gps.csv] [--refit]
    hmpf-index add --index maps/campus --experiences fleet.log [more.log ...] [--dry-run]
    hmpf-index remove --index maps/campus img0001.jpg img0002.jpg
    hmpf-index remove --index maps/campus --experiences-from vehicle=V|log=L|before=TIME
    hmpf-index verify --index maps/campus [--index-version v0002]   (default: every version)
    hmpf-index info --index maps/campus [--index-version v0002]
    hmpf-index use --index maps/campus v0002
    hmpf-index shard --index maps/city --shards 4 --overlap 20 [--by position] --out DIR
    hmpf-index list|gc --index maps/campus
    hmpf-index --version

Exit status: 0 success, 1 ``verify`` found a problem, 2 bad input or a failed operation (a
corrupt version among them: ``use`` it, or ``add`` / ``remove`` from it), 130 interrupted (the
current version is untouched; ``--resume`` continues).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

# Only light modules at import time: the heavy ones (numpy, OpenCV, h5py, FAISS) load inside
# ``run``, so Ctrl-C while they load is one line and exit 130 too, and --version is instant.
from hmpf.cli.args import cache_from_args, default_cache_dir
from hmpf.cli.common import add_version, run
from hmpf.errors import DatasetError, HmpfError

if TYPE_CHECKING:
    from indexer.build import BuildOptions
    from indexer.distributed import RayOptions

PROG = "hmpf-index"
INTERRUPTED = "interrupted; the current version is untouched (rerun with --resume to continue)"


# ``METHOD=VALUE``: a method id, then the value. A FAISS parameter value is itself
# ``name=value[,name=value]``, so there the method form needs a second ``name=`` after it.
_FOR_METHOD = re.compile(r"([A-Za-z_]\w*)=(.+)")
_PARAMS_FOR_METHOD = re.compile(r"([A-Za-z_]\w*)=([A-Za-z_]\w*=.*)")


def _pairs(values: Sequence[str] | None, pattern: re.Pattern[str] = _FOR_METHOD) -> dict[str, str]:
    """``["IVF1024,Flat", "gist=HNSW32"]`` -> ``{"*": "IVF1024,Flat", "gist": "HNSW32"}``;
    with ``_PARAMS_FOR_METHOD``: ``["nprobe=16", "gem=nprobe=32"]`` ->
    ``{"*": "nprobe=16", "gem": "nprobe=32"}``."""
    out = {}
    for v in values or []:
        m = pattern.fullmatch(v)
        if m:
            out[m.group(1)] = m.group(2)
        else:
            out["*"] = v
    return out


def _add_write_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--faiss",
        action="append",
        metavar="[METHOD=]FACTORY",
        help="FAISS factory string for tier-1 methods (default Flat = exact); e.g. "
        "'IVF1024,Flat' for all or 'gist=HNSW32' for one; repeatable",
    )
    p.add_argument(
        "--faiss-params",
        action="append",
        metavar="[METHOD=]PARAMS",
        help="FAISS search parameters stored with the index, e.g. 'nprobe=16'",
    )
    p.add_argument(
        "--precision",
        choices=["exact", "compact"],
        default="exact",
        help="exact: float16 only where lossless (default); compact: float16 for all floats",
    )
    p.add_argument("--strict", action="store_true", help="fail on an unreadable image")
    p.add_argument("--workers", type=int, default=None, help="extraction processes")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="extract on Ray (pip install 'hmpf[ray]'): a local instance of --workers CPUs, "
        "or the cluster at ADDRESS (HOST:PORT or auto); the version is the same as without",
    )


class _RenamedFlag(argparse.Action):
    """``info|verify --version NAME`` (before ``--version`` printed the program's version)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        parser.error("--version NAME is now --index-version NAME")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    add_version(p)
    sub = p.add_subparsers(dest="command", required=True)

    b = sub.add_parser("build", help="extract every image and publish a new version")
    b.add_argument(
        "--config",
        required=True,
        help="a preset name (e.g. default), a hierarchy YAML file, or auto: chosen from the "
        "references (and --metadata's route order / GPS) alone, on pseudo-queries made from "
        "them; why is recorded in the version's manifest (hmpf-index info [--json])",
    )
    b.add_argument("--images", required=True, help="folder of reference images")
    b.add_argument("--metadata", help="CSV: name[,lat,lon,heading,timestamp,sequence]")
    b.add_argument("--index", required=True, help="index folder (created if missing)")
    b.add_argument("--resume", action="store_true", help="continue an interrupted build")
    b.add_argument(
        "--seed", type=int, default=0, help="with --config auto: the choice's seed (default 0)"
    )
    b.add_argument(
        "--cache-dir",
        help="with --config auto or the map prior: the feature cache the choice or the "
        f"pseudo-queries read and fill (default {default_cache_dir()}), so a rerun or "
        "--resume does not extract them again",
    )
    b.add_argument(
        "--no-cache", action="store_true", help="with --config auto or the map prior: no cache"
    )
    b.add_argument(
        "--map-prior",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="store the config's recall@1 on pseudo-queries made from the references (the "
        "acceptance models' map-level prior; extracts the pseudo-queries and, again, up to "
        "1,000 references; hmpf-index info shows it). Default: when the config's acceptance "
        "models read it (the default preset's do); --no-map-prior: never (hmpf-serve then "
        "uses the models' conservative fallback)",
    )
    _add_write_options(b)

    a = sub.add_parser(
        "add", help="publish a version with more places, or with the fleet's experiences"
    )
    a.add_argument("--index", required=True)
    what = a.add_mutually_exclusive_group(required=True)
    what.add_argument("--images", help="folder of new reference images (new places)")
    what.add_argument(
        "--experiences",
        nargs="+",
        metavar="LOG",
        help="experience logs the service recorded: their frames become experiences of the "
        "places they were localised at (gated: confidence, agreement, duplicates, cap)",
    )
    a.add_argument("--metadata", help="with --images: CSV as for build")
    a.add_argument("--refit", action="store_true", help="refit fitted parameters on all images")
    a.add_argument("--resume", action="store_true", help="continue an interrupted add")
    merge = a.add_argument_group("with --experiences (defaults: the config's experiences:)")
    merge.add_argument(
        "--dry-run", action="store_true", help="report what would be added; write nothing"
    )
    merge.add_argument("--min-p-correct", type=float, metavar="P", help="confidence gate")
    merge.add_argument(
        "--agreement-window",
        type=int,
        metavar="W",
        help="agreement gate: places along the route (negative: off)",
    )
    merge.add_argument(
        "--duplicate-similarity", type=float, metavar="S", help="near-duplicate gate (cosine)"
    )
    merge.add_argument(
        "--max-per-place", type=int, metavar="N", help="images per place, original included"
    )
    merge.add_argument(
        "--no-interpolate-places",
        dest="interpolate_places",
        action="store_const",
        const=False,
        help="keep every frame at its recorded place (do not place a frame between its time "
        "neighbours)",
    )
    merge.add_argument(
        "--no-place-leads",
        dest="place_leads",
        action="store_const",
        const=False,
        help="leave out the lead frames (a lock's lead-in the service recorded before a "
        "vehicle's recorded frame) instead of placing them from the frames after them",
    )
    merge.add_argument(
        "--no-gates",
        action="store_true",
        help="open every gate: merge each readable frame of a known place (to measure them)",
    )
    _add_write_options(a)

    r = sub.add_parser("remove", help="publish a version without some images or experiences")
    r.add_argument("--index", required=True)
    r.add_argument(
        "names", nargs="*", help="image file names to drop (a place: with its experiences)"
    )
    r.add_argument(
        "--experiences-from",
        action="append",
        metavar="KEY=VALUE",
        help="drop the experiences from vehicle=V, log=L or before=TIME (epoch seconds or ISO "
        "8601); repeatable: values of one key are alternatives, different keys all apply",
    )

    for name, helptext, default in (
        ("verify", "recompute checksums and shapes", "every version"),
        ("info", "show a version's manifest", "current"),
    ):
        s = sub.add_parser(name, help=helptext)
        s.add_argument("--index", required=True)
        s.add_argument(
            "--index-version",
            metavar="NAME",
            help=f"index version, e.g. v0002 (default: {default})",
        )
        s.add_argument("--version", nargs="?", action=_RenamedFlag, help=argparse.SUPPRESS)
        if name == "info":
            s.add_argument("--json", action="store_true", help="print JSON")
            s.add_argument("--names", action="store_true", help="also list reference names")

    u = sub.add_parser("use", help="make a version current (verified first; atomic)")
    u.add_argument("--index", required=True)
    u.add_argument("name", metavar="VERSION", help="the version to use, e.g. v0002")

    sh = sub.add_parser(
        "shard", help="split the current version into region shards (hmpf-serve shards)"
    )
    sh.add_argument("--index", required=True)
    sh.add_argument("--shards", type=int, required=True, metavar="N", help="number of shards")
    sh.add_argument(
        "--overlap",
        type=int,
        default=0,
        metavar="K",
        help="places along the route on either side of a border held by both neighbours",
    )
    sh.add_argument(
        "--by",
        choices=["route", "position"],
        default="route",
        help="cut stretches of the routes (default) or of a curve through the places' "
        "positions (each shard a compact region)",
    )
    sh.add_argument("--out", required=True, help="the shard folder (created if missing)")

    ls = sub.add_parser("list", help="list versions")
    ls.add_argument("--index", required=True)

    g = sub.add_parser("gc", help="delete old versions (never the current one)")
    g.add_argument("--index", required=True)
    g.add_argument("--keep", type=int, default=0, help="also keep the N newest old versions")
    g.add_argument("--dry-run", action="store_true")
    return p


def _options(args: argparse.Namespace) -> BuildOptions:
    from indexer.build import BuildOptions

    return BuildOptions(
        faiss=_pairs(args.faiss),
        faiss_params=_pairs(args.faiss_params, _PARAMS_FOR_METHOD),
        precision=args.precision,
        strict=args.strict,
        workers=args.workers,
        progress=not args.quiet,
        ray=_ray_options(args),
    )


def _ray_options(args: argparse.Namespace) -> RayOptions | None:
    if args.ray is None:
        return None
    from indexer.distributed import RayOptions, require_ray

    require_ray()  # before any image is read
    return RayOptions(address=None if args.ray == "local" else args.ray, workers=args.workers)


def _print_info(args: argparse.Namespace) -> int:
    from hmpf.index.reader import IndexReader
    from indexer import maintenance

    data = maintenance.info(args.index, args.index_version)
    if args.names:
        with IndexReader(args.index, args.index_version) as reader:
            data["names"] = reader.refs.names
    if args.json:
        print(json.dumps(data, indent=1))
        return 0
    s = data.get("summary", {})
    print(
        f"version {data['version']} ({data['operation']}, parent {data['parent']}) "
        f"{data['created']}"
    )
    print(f"config {data['config']['name']} sha256 {data['config']['sha256'][:16]}")
    print(f"references {data['images']['count']}, metadata: {data['images']['metadata_columns']}")
    places = data.get("places") or {"count": data["images"]["count"], "experiences": 0}
    print(f"places {places['count']}, experiences {places['experiences']}")
    if data.get("experiences"):
        from indexer.build import experience_lines

        for line in experience_lines(data["experiences"]):
            print(line)
    choice = data.get("choice")
    if choice:
        print(
            f"chosen by --config auto (seed {choice['seed']}, {len(choice['candidates'])} "
            f"candidates, {choice['time_s']['total_s']:.0f} s): {choice['chosen']['hierarchy']}: "
            f"{choice['chosen']['why']} (all of it: --json, key choice)"
        )
    prior = data.get("map_prior")
    if prior:
        print(map_prior_line(prior))
    print(f"bytes {s.get('bytes_total')}  built in {s.get('seconds', 0):.1f} s")
    for mid, m in data["methods"].items():
        fa = m.get("faiss") or {}
        print(f"  {mid:<10} {m['kind']:<6} v{m['version']}  faiss {fa.get('factory', '-')}")
    for sk in s.get("skipped", []):
        print(f"  skipped {sk['name']}: {sk['reason']}")
    for n in data.get("names", []):
        print(n)
    return 0


def map_prior_line(entry: dict[str, object]) -> str:
    """``hmpf-index info``'s line for a manifest's ``map_prior`` entry."""
    where = f", computed in {entry['computed_in']}" if entry.get("computed_in") else ""
    if entry.get("map_prior") is None:
        return f"map prior: none ({entry.get('why_none', 'not computed')}){where}"
    return (
        f"map prior {entry['map_prior']:+.2f}: recall@1 {entry['recall_at_1']:.3f} on "
        f"{entry['pseudo_queries']} pseudo-queries of the references{where}"
    )


def _verify(args: argparse.Namespace) -> int:
    """One version (``--index-version``) or every version; exit 1 when any is corrupt."""
    from hmpf.index import layout
    from indexer import maintenance

    if args.index_version is not None:
        problems = maintenance.verify(args.index, args.index_version)
        for line in problems:
            print(f"CORRUPT {line}")
        print("ok" if not problems else f"{len(problems)} problem(s)")
        return 1 if problems else 0
    results = maintenance.verify_all(args.index)
    try:
        current = layout.current_version(Path(args.index))
    except HmpfError:
        current = None
    for version, problems in results.items():
        mark = " (current)" if version == current else ""
        for line in problems:
            print(f"CORRUPT {version}{mark}: {line}")
        if not problems:
            print(f"{version}{mark}: ok")
    bad = [v for v, p in results.items() if p]
    n = sum(v != "CURRENT" for v in results)
    checked = f"checked {n} version(s): every file's size and sha256, then shapes"
    print(f"ok: {checked}" if not bad else f"corrupt: {', '.join(bad)}; {checked}")
    return 1 if bad else 0


_MERGE_KNOBS = (
    "min_p_correct",
    "agreement_window",
    "duplicate_similarity",
    "max_per_place",
    "interpolate_places",
    "place_leads",
)


def _images_only(args: argparse.Namespace) -> None:
    """Refuse the merge's options without --experiences (they would be silently ignored)."""
    given = [k for k in _MERGE_KNOBS if getattr(args, k) is not None]
    given += [k for k in ("dry_run", "no_gates") if getattr(args, k)]
    if given:
        names = {"interpolate_places": "no_interpolate_places", "place_leads": "no_place_leads"}
        flags = ", ".join("--" + names.get(k, k).replace("_", "-") for k in given)
        raise DatasetError(f"{flags}: only with --experiences")


def _merge(args: argparse.Namespace) -> int:
    from indexer.experiences import LogRecords, merge

    if args.metadata or args.refit:
        raise DatasetError("--metadata and --refit go with --images, not --experiences")
    report = merge(
        args.index,
        LogRecords(args.experiences),
        settings={k: getattr(args, k) for k in _MERGE_KNOBS},
        gates=not args.no_gates,
        options=_options(args),
        dry_run=args.dry_run,
        resume=args.resume,
    )
    for line in report.lines():
        print(line)
    return 0


def _run(args: argparse.Namespace) -> int:
    from indexer import maintenance
    from indexer.build import add, build, remove

    cmd = args.command
    if cmd == "build":
        if args.config != "auto" and args.seed != 0:
            raise HmpfError("--seed can only go with --config auto")
        if args.config != "auto" and args.map_prior is False and (args.cache_dir or args.no_cache):
            raise HmpfError("--cache-dir and --no-cache go with --config auto or the map prior")
        uses_cache = args.config == "auto" or args.map_prior is not False
        summary = build(
            args.config,
            args.images,
            args.index,
            metadata=args.metadata,
            options=_options(args),
            resume=args.resume,
            seed=args.seed,
            cache=cache_from_args(args) if uses_cache else None,
            with_map_prior=args.map_prior,
        )
    elif cmd == "add" and args.experiences:
        return _merge(args)
    elif cmd == "add":
        _images_only(args)
        summary = add(
            args.index,
            args.images,
            metadata=args.metadata,
            options=_options(args),
            refit=args.refit,
            resume=args.resume,
        )
    elif cmd == "remove" and args.experiences_from:
        if args.names:
            raise DatasetError("give image names or --experiences-from, not both")
        from indexer.experiences import remove_experiences

        summary = remove_experiences(args.index, args.experiences_from)
    elif cmd == "remove":
        if not args.names:
            raise DatasetError("name the images to remove, or give --experiences-from")
        summary = remove(args.index, args.names)
    elif cmd == "verify":
        return _verify(args)
    elif cmd == "shard":
        from indexer.shard import split

        for line in split(args.index, args.shards, args.overlap, args.out, args.by).lines():
            print(line)
        return 0
    elif cmd == "use":
        old, new = maintenance.use(args.index, args.name)
        print(
            f"CURRENT: {old or '-'} -> {new} (verified); a running hmpf-serve switches on "
            "POST /v1/index/reload, or by itself with watch_current_s (replicas)"
        )
        return 0
    elif cmd == "info":
        return _print_info(args)
    elif cmd == "list":
        for v in maintenance.list_versions(args.index):
            mark = "*" if v["current"] else " "
            print(
                f"{mark} {v['version']}  {v.get('operation', '?'):<7} {v.get('images')} refs  "
                f"{v.get('created')}  {v.get('error', '')}"
            )
        return 0
    else:  # gc
        for p in maintenance.gc(args.index, args.keep, args.dry_run):
            print(("would delete " if args.dry_run else "deleted ") + p)
        return 0
    for line in summary.lines():
        print(line)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run(PROG, lambda: _run(args), interrupted=INTERRUPTED)


if __name__ == "__main__":
    sys.exit(main())
