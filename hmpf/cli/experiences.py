"""``hmpf-experiences``: look into an experience log and delete from it.

    hmpf-experiences list /var/lib/hmpf/experiences
    hmpf-experiences prune /var/lib/hmpf/experiences --vehicle car-17 --dry-run
    hmpf-experiences prune /var/lib/hmpf/experiences --older-than 30

``list`` prints what the log holds: its records per vehicle (with their time range), per
index version, per mode and per place, and what reading it met besides (torn tails: writes
cut short; damaged stretches: bytes changed on disk); ``--json`` prints the same as JSON.
``prune`` deletes a vehicle's records, or those received more than DAYS days ago (the
frames are people's camera images: retention and deletion), safely beside a running
service writing the log (records in the segment it is writing are left, and said so: run
prune again later). ``--dry-run`` says what would go, changing nothing.

Exit codes: 0 done, 2 not an experience log (one line, no traceback), 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from collections.abc import Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from hmpf.cli.common import add_version, run
from hmpf.errors import HmpfError
from hmpf.experience_log import LogStats, Record, log_id, prune, read_log

__all__ = ["build_parser", "main", "summarize"]

PROG = "hmpf-experiences"
DAY_S = 86400.0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Look into an experience log (frames the service recorded for the map) "
        "and delete records by vehicle or by age.",
    )
    add_version(ap)
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    ls = sub.add_parser("list", help="what the log holds: per vehicle, version, mode, place")
    ls.add_argument("log", type=Path, metavar="LOG", help="the log's folder")
    ls.add_argument("--json", action="store_true", help="print the summary as JSON")
    pr = sub.add_parser("prune", help="delete a vehicle's records, or those older than DAYS")
    pr.add_argument("log", type=Path, metavar="LOG", help="the log's folder")
    which = pr.add_mutually_exclusive_group(required=True)
    which.add_argument("--vehicle", metavar="V", help="delete every record of vehicle V")
    which.add_argument(
        "--older-than",
        type=float,
        metavar="DAYS",
        help="delete the records received more than DAYS days ago",
    )
    pr.add_argument("--dry-run", action="store_true", help="say what would go; change nothing")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "list":
        return run(PROG, lambda: _list(args))
    return run(PROG, lambda: _prune(args), interrupted="interrupted (each segment is whole)")


def _list(args: argparse.Namespace) -> int:
    stats = LogStats()
    summary = summarize(log_id(args.log), read_log(args.log, stats=stats), stats)
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print("\n".join(_lines(args.log, summary)))
    return 0


def _prune(args: argparse.Namespace) -> int:
    if args.older_than is not None and not (
        math.isfinite(args.older_than) and args.older_than >= 0
    ):
        raise HmpfError(f"--older-than must be a number of days >= 0 (got {args.older_than})")
    older = None if args.older_than is None else args.older_than * DAY_S
    report = prune(args.log, vehicle=args.vehicle, older_than_s=older, dry_run=args.dry_run)
    verb = "would remove" if report.dry_run else "removed"
    what = (
        f"of vehicle {args.vehicle!r}"
        if args.vehicle is not None
        else (f"received more than {args.older_than:g} days ago")
    )
    print(f"{verb} {report.removed} records {what}; {report.kept} kept")
    if not report.dry_run and (report.rewritten or report.deleted):
        print(f"rewrote {report.rewritten} segments, deleted {report.deleted}")
    if report.pending:
        print(
            f"{report.pending} more are in the segment a running service is writing: they are "
            "left; run prune again once it has started a new segment or stopped"
        )
    return 0


def summarize(log: str, records: Iterable[Record], stats: LogStats) -> dict[str, Any]:
    """What a log holds, as plain data (``stats`` is filled as ``records`` is read)."""
    vehicles: dict[str, dict[str, Any]] = {}
    places: Counter[tuple[str, int, str]] = Counter()
    versions: Counter[str] = Counter()
    modes: Counter[str] = Counter()
    first = last = None
    n = 0
    image_bytes = 0
    for rec in records:
        n += 1
        image_bytes += len(rec.image)
        t = rec.age_time
        v = vehicles.setdefault(rec.vehicle, {"records": 0, "first": t, "last": t})
        v["records"] += 1
        v["first"], v["last"] = min(v["first"], t), max(v["last"], t)
        first = t if first is None else min(first, t)
        last = t if last is None else max(last, t)
        places[(rec.index_version, rec.place, rec.place_name)] += 1
        versions[rec.index_version] += 1
        modes[rec.mode] += 1
    return {
        "log": log,
        "records": n,
        "image_bytes": image_bytes,
        "bytes": stats.bytes,
        "segments": stats.segments,
        "torn": stats.torn,
        "damaged": stats.damaged,
        "skipped_bytes": stats.skipped_bytes,
        "first": first,
        "last": last,
        "vehicles": dict(sorted(vehicles.items())),
        "versions": dict(sorted(versions.items())),
        "modes": dict(sorted(modes.items())),
        "places": [
            {"index_version": ver, "place": p, "name": name, "records": c}
            for (ver, p, name), c in sorted(places.items())
        ],
    }


def _when(t: float | None) -> str:
    if t is None or not math.isfinite(t):
        return "-"
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _lines(path: Path, s: dict[str, Any]) -> list[str]:
    out = [
        f"log {s['log']} ({path}): {s['records']} records, {s['segments']} segments, "
        f"{s['bytes'] / 1e6:.1f} MB",
        f"received {_when(s['first'])} .. {_when(s['last'])}",
        f"torn tails: {s['torn']}, damaged stretches: {s['damaged']} "
        f"({s['skipped_bytes']} bytes skipped)",
    ]
    if s["records"]:
        out.append("versions: " + ", ".join(f"{k} {v}" for k, v in s["versions"].items()))
        out.append("modes: " + ", ".join(f"{k} {v}" for k, v in s["modes"].items()))
        out.append("vehicles:")
        width = max(len(k or "(none)") for k in s["vehicles"])
        for k, v in s["vehicles"].items():
            out.append(
                f"  {k or '(none)':<{width}}  {v['records']:>7}  "
                f"{_when(v['first'])} .. {_when(v['last'])}"
            )
        out.append("places:")
        for p in s["places"]:
            out.append(f"  {p['index_version']}  {p['place']:>6}  {p['name']}  {p['records']}")
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
