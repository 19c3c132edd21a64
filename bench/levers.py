"""The accuracy levers, each alone and combined, in one table.

    python -m bench.levers [--only NAME ...] [--nordland-configs NAME ...] [--out F.json]
    python -m bench.levers --time-only [--images 20]      (ms per query only: a quiet machine)
    python -m bench.levers --table F.json                 (print the table of an earlier run)

Configs: the presets ``default-lite0`` (the baseline: the default until 2026-11-26, which
every lever was measured against), ``default`` (the current one, chosen from these levers),
``netvlad-lite1``, ``thumbnails`` and ``calibrated/nordland_handcrafted``, and every YAML in
``bench/levers/`` (one per lever; each file's header says which lever and where its settings
were chosen). NAME is a preset name or
a YAML's stem (``inliers``, ``olo_regions50``, ...).

Every config goes through :func:`choose_default.measure` (the machinery of
``bench/choose_default.py``): recall@1 (+-2 frames) of the hierarchy on the training and the
test part of each Gardens Point protocol (``blocks`` split of 20 frames, each part its own
map, fitted parameters fitted on that part's references); for the ``--nordland-configs`` also
Nordland summer -> winter 64x32 (``blocks`` split of 100 frames, 1800 training / 1776 test
queries, as ``calibrated/nordland_handcrafted`` and ``thumbnails`` were chosen); the query's
extraction on one compute thread (median over ``--images`` day_right images); and the bytes an
index stores per reference (``exact`` precision; :func:`inliers.bytes_per_reference` on the
first Gardens Point protocol's test part, and on Nordland's test part where measured).

Training mean: Gardens Point's three training parts (the choice rule: a config is proposed
only if it beats the baseline there). Test figures are compared with the baseline by an exact
paired sign test on the pooled Gardens Point test queries (300), Nordland's with
``calibrated/nordland_handcrafted`` (the previous advice for thumbnails) on its 1776.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from bench.choose_default import load_protocols, measure, timing_images
from bench.harness import (
    ROOT,
    add_cache_dir,
    add_json,
    machine,
    parser,
    provenance,
    record,
    write_json,
)
from bench.inliers import bytes_per_reference
from bench.one_pass import query_ms
from hmpf.config import HierarchyConfig, build_methods, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS
from hmpf.evaluation.calibrate import paired_test
from hmpf.evaluation.evaluate import EvalData, prepare
from hmpf.evaluation.study import ScoreBank
from hmpf.features import FeatureCache
from hmpf.runtime import set_cnn_runtime

LEVERS = ROOT / "bench" / "levers"
PRESETS = (
    "default-lite0",
    "default",
    "netvlad-lite1",
    "thumbnails",
    "calibrated/nordland_handcrafted",
)
#: The levers were measured against the default of their time, now the preset default-lite0.
BASELINE = "default-lite0"
NORDLAND_BASELINE = "calibrated/nordland_handcrafted"
NORDLAND_DEFAULT = (
    "default-lite0",
    "default",
    "netvlad-lite1",
    "thumbnails",
    "calibrated/nordland_handcrafted",
    "combined",
)
#: Nordland's stretch for the ``blocks`` split (as the thumbnail configs were chosen).
NORDLAND_BLOCK = 100
GP = list(GARDENS_POINT_PROTOCOLS)
NL = "nordland_s_w"


def all_configs() -> dict[str, str]:
    """Row name -> what :func:`hmpf.config.load_config` takes (presets first, then the
    lever YAMLs by name)."""
    out = {p: p for p in PRESETS}
    out.update({f.stem: str(f) for f in sorted(LEVERS.glob("*.yaml"))})
    return out


def reference_bytes(config: HierarchyConfig, data: EvalData, cache: FeatureCache) -> float:
    """Bytes per reference an index of ``data``'s references stores for ``config``: each
    reference's own descriptors (an index applies ``dba`` when it loads, so the config is
    measured with ``dba`` removed: the augmented means are not what is stored)."""
    dump = config.model_dump()
    for params in dump["methods"].values():
        params.pop("dba", None)
    stored = HierarchyConfig.model_validate(dump)
    prep = prepare(build_methods(stored), data, cache=cache)
    feats = {m: (prep.db[m], prep.queries[m]) for m in prep.methods}
    bank = ScoreBank(dict(prep.methods), {}, np.asarray(data.gt, bool), data, feats)
    return bytes_per_reference(bank, stored)


def sign(a: list[bool], b: list[bool]) -> dict[str, Any]:
    return paired_test(np.asarray(a, bool), np.asarray(b, bool))


def take_ms(report: dict[str, Any], path: Path) -> None:
    """Replace the rows' ms per query by those of the ``--time-only`` run in ``path``."""
    timed = json.loads(path.read_text())
    for name, row in report["rows"].items():
        if name in timed["rows"]:
            row["query_ms_measured_here"] = row.get("query_ms")
            row["query_ms"] = timed["rows"][name]["query_ms"]
            row["query_ms_from"] = str(path)
    keys = ("machine", "load_start", "load_end", "images_timed")
    report["ms_from"] = {"file": str(path), **{k: timed.get(k) for k in keys}}


def caption(report: dict[str, Any]) -> str:
    timed = report.get("ms_from", report)
    src = f", {timed['file']}" if "file" in timed else ""
    return (
        "recall@1 (+-2 frames) on the test parts; ms: query extraction on one thread (median of "
        f"{timed['images_timed']} day_right images{src}; load average "
        f"{timed['load_start'][0]:.1f} at start); bytes / ref: exact precision, GP dr -> nr test "
        f"part (NL: Nordland test part); test vs {BASELINE}: pooled GP test queries, won / "
        "lost, sign test p"
    )


def table(out: dict[str, Any]) -> list[str]:
    """The markdown table of ``out`` (row name -> figures)."""
    lines = [
        "| config | GP dr -> nr | GP dl -> nr | GP dl -> dr | Nordland 64x32 | ms / query "
        f"| bytes / ref | training mean (GP) | test mean (GP) | test vs {BASELINE} |",
        "|---|---|---|---|---|---:|---:|---:|---:|---|",
    ]
    base = out.get(BASELINE)
    nl_base = out.get(NORDLAND_BASELINE)
    for name, row in out.items():
        ms = f"{row['query_ms']:.1f}" if "query_ms" in row else ""
        if "test" not in row:
            lines.append(f"| {name} | | | | | {ms} | | | | |")
            continue
        gp = [f"{row['test'][p]:.3f}" for p in GP]
        nl = ""
        if NL in row["test"]:
            nl = f"{row['test'][NL]:.3f}"
            if nl_base is not None and name != NORDLAND_BASELINE and NL in nl_base.get("test", {}):
                t = sign(row["flags"]["test"][NL], nl_base["flags"]["test"][NL])
                nl += f" ({t['wins']} / {t['losses']}, p {t['p']:.2g} vs nordland_handcrafted)"
        size = f"{row['bytes_gp']:,.0f}"
        if "bytes_nl" in row:
            size += f" (NL {row['bytes_nl']:,.0f})"
        vs = ""
        if base is not None and name != BASELINE and "test" in base:
            t = sign(row["test_flags"], base["test_flags"])
            vs = f"{t['wins']} / {t['losses']}, p {t['p']:.2g}"
        lines.append(
            f"| {name} | {' | '.join(gp)} | {nl} | {ms} | {size} | {row['train_mean']:.3f} "
            f"| {row['test_mean']:.3f} | {vs} |"
        )
    return lines


def arguments(names: dict[str, Any]) -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    ap = parser(__doc__)
    ap.add_argument("--only", nargs="+", default=None, choices=list(names), metavar="NAME")
    ap.add_argument(
        "--nordland-configs",
        nargs="*",
        default=list(NORDLAND_DEFAULT),
        metavar="NAME",
        help="configs also measured on Nordland summer -> winter (default: %(default)s)",
    )
    ap.add_argument("--time-only", action="store_true", help="ms per query only, no accuracy")
    ap.add_argument("--images", type=int, default=10, help="images timed (day_right)")
    add_cache_dir(ap)
    add_json(ap, "--out", type=Path, help="write the figures as JSON")
    ap.add_argument("--table", type=Path, default=None, help="print the table of this JSON")
    ap.add_argument(
        "--reuse",
        type=Path,
        nargs="*",
        default=[],
        help="earlier --out files: their rows (accuracy, ms) are taken as measured there instead "
        "of measured again (Nordland too where the row has it); the first file with a row wins",
    )
    ap.add_argument(
        "--ms-from",
        type=Path,
        default=None,
        help="a --time-only run's --out: its ms per query replace the ones measured here (one "
        "timing run for every row, e.g. on a quieter machine)",
    )
    return ap, ap.parse_args()


def print_table(report: dict[str, Any], ms_from: Path | None) -> None:
    if ms_from is not None:
        take_ms(report, ms_from)
    print(f"\n{caption(report)}\n")
    print("\n".join(table(report["rows"])))


def reused_rows(paths: list[Path], chosen: list[str]) -> dict[str, Any]:
    """The rows of earlier ``--out`` files to take as measured there (the first file wins)."""
    reused: dict[str, Any] = {}
    for f in paths:
        earlier = json.loads(f.read_text())
        for name, row in earlier["rows"].items():
            if name in chosen and name not in reused and "test" in row:
                reused[name] = {**row, "reused_from": str(f)}
    return reused


def measure_gp(
    config: HierarchyConfig, full: Any, parts: Any, cache: FeatureCache, timing: Any
) -> dict[str, Any]:
    """A config's row on Gardens Point: accuracy, ms per query and bytes per reference."""
    row, flags = measure(config, full, parts, cache, timing, protocols=GP, whole=False)
    row["flags"] = {part: {p: f.tolist() for p, f in fl.items()} for part, fl in flags.items()}
    row["bytes_gp"] = reference_bytes(config, parts[GP[0]][1], cache)
    return row


def add_nordland(
    row: dict[str, Any], config: HierarchyConfig, full: Any, parts: Any, cache: FeatureCache
) -> None:
    """Nordland summer -> winter's figures into ``row``."""
    nl_row, flags = measure(config, full, parts, cache, None, protocols=[NL], whole=False)
    for part in ("train", "test"):
        row[part][NL] = nl_row[part][NL]
        row["flags"][part][NL] = flags[part][NL].tolist()
    row["bytes_nl"] = reference_bytes(config, parts[NL][1], cache)


def main() -> int:
    names = all_configs()
    ap, args = arguments(names)
    if args.table is not None:
        print_table(json.loads(args.table.read_text()), args.ms_from)
        return 0
    unknown = set(args.nordland_configs) - set(names)
    if unknown:
        ap.error(f"unknown --nordland-configs: {', '.join(sorted(unknown))}")
    chosen = args.only or list(names)
    if BASELINE not in chosen and not args.time_only:
        chosen = [BASELINE, *chosen]  # the sign tests need it
    set_cnn_runtime("onnx")
    print(f"Machine: {machine()}", flush=True)
    print(f"Load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    prov = provenance(args=args)
    report: dict[str, Any] = {
        "load_start": list(os.getloadavg()),
        "images_timed": args.images,
        "rows": {},
    }
    rows: dict[str, Any] = report["rows"]
    reused = {} if args.time_only else reused_rows(args.reuse, chosen)
    report["reused"] = {n: r["reused_from"] for n, r in reused.items()}

    def save() -> None:
        if args.out:
            write_json(args.out, record(report, prov=prov))

    timing = timing_images(args.images)
    if args.time_only:
        for name in chosen:
            rows[name] = {"query_ms": query_ms(load_config(names[name]), *timing)}
            print(f"{name}: {rows[name]['query_ms']:.1f} ms/query", flush=True)
            save()
    else:
        cache = FeatureCache(args.cache_dir)
        nl_wanted = [n for n in chosen if n in args.nordland_configs]
        full, parts = load_protocols(bool(nl_wanted), NORDLAND_BLOCK)
        # Gardens Point for every config first; Nordland (slow for CNN configs) after.
        for name in chosen:
            config = load_config(names[name])
            if name in reused:  # accuracy as measured there; bytes (cheap) measured again
                rows[name] = row = reused[name]
                row["bytes_gp"] = reference_bytes(config, parts[GP[0]][1], cache)
                if NL in row["test"] and NL in parts:
                    row["bytes_nl"] = reference_bytes(config, parts[NL][1], cache)
                print(f"{name}: reused from {row['reused_from']}", flush=True)
                continue
            rows[name] = row = measure_gp(config, full, parts, cache, timing)
            print(
                f"{name}: {row['query_ms']:.1f} ms/query, GP train {row['train_mean']:.3f}, "
                f"test {row['test_mean']:.3f}, {row['bytes_gp']:,.0f} bytes/ref",
                flush=True,
            )
            save()
        for name in nl_wanted:
            row = rows[name]
            if NL in row["test"]:
                continue  # reused with Nordland
            add_nordland(row, load_config(names[name]), full, parts, cache)
            print(
                f"{name}: Nordland train {row['train'][NL]:.3f}, test {row['test'][NL]:.3f}, "
                f"{row['bytes_nl']:,.0f} bytes/ref",
                flush=True,
            )
            save()
    report["load_end"] = list(os.getloadavg())
    print_table(report, args.ms_from)
    save()
    print(f"\nLoad average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
