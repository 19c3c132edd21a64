"""What one query reads from disk, and what it costs cold and warm.

    .venv/bin/python -m bench.query_reads --index INDEX --queries DIR [--n 50] [--json F]

Opens the index's current version in this process (:class:`hmpf.index.IndexReader`, as a
replica does: rows that are read on demand stay on disk), extracts ``--n`` query frames once,
then runs the hierarchy for each of them twice over:

* **cold**: before each query the version's files are dropped from the page cache
  (``posix_fadvise(DONTNEED)``, which needs no privileges) and the reader's own cache of
  decoded local features is emptied, so every row the query needs comes from the disk;
* **warm**: the same queries again, right after, with everything they read still cached.

For each pass it prints the median and p99 of the hierarchy's time (FAISS search, exact
re-scoring, later tiers; extraction excluded: it does not read the index) and what a
query read through the reader (:attr:`IndexReader.read_stats`: rows and bytes of the
matrices held on disk, and local features), which is the same cold or warm: the cache
changes where the bytes come from, not which.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import add_json, machine, parser, write_record
from hmpf.datasets import list_images
from hmpf.imageio import load_image
from hmpf.index import IndexReader


def drop_page_cache(version_dir: Path) -> None:
    """Ask the kernel to drop the version's files from the page cache."""
    for p in version_dir.rglob("*"):
        if p.is_file():
            fd = os.open(p, os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def run_pass(reader: IndexReader, feats: list[dict[str, Any]], cold: bool) -> dict[str, Any]:
    """Time the hierarchy for every query; per-query reads from ``read_stats``."""
    hier = reader.hierarchy()
    ms, rows, nbytes = [], [], []
    for f in feats:
        if cold:
            drop_page_cache(reader.path)
            reader.local_cache = type(reader.local_cache)(reader.local_cache.max_bytes)
        before = (reader.read_stats.rows, reader.read_stats.bytes)
        t = time.perf_counter()
        hier.run(reader.scorer(f), reader.n)
        ms.append((time.perf_counter() - t) * 1e3)
        rows.append(reader.read_stats.rows - before[0])
        nbytes.append(reader.read_stats.bytes - before[1])
    return {
        "p50_ms": statistics.median(ms),
        "p99_ms": float(np.percentile(ms, 99)),
        "rows_per_query": statistics.median(rows),
        "kib_per_query": statistics.median(nbytes) / 1024,
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = parser(__doc__)
    ap.add_argument("--index", required=True, type=Path)
    ap.add_argument("--queries", required=True, type=Path, help="folder of query images")
    ap.add_argument("--n", type=int, default=50, help="queries (the first N of the folder)")
    add_json(ap)
    args = ap.parse_args(argv)
    with IndexReader(args.index) as reader:
        images = list_images(args.queries)[: args.n]
        feats = [reader.extract_query(load_image(p)) for p in images]
        run_pass(reader, feats[:3], cold=False)  # first-use costs (FAISS load, imports)
        cold = run_pass(reader, feats, cold=True)
        warm = run_pass(reader, feats, cold=False)
        out = {
            "index": str(reader.path),
            "references": reader.n_rows,
            "config": reader.config.name,
            "config_digest": reader.config.digest()[:12],
            "queries": len(feats),
            "machine": machine(),
            "on_demand": sorted(m for m in reader.methods if reader.on_demand(m)),
            "cold": cold,
            "warm": warm,
        }
    print(
        f"{out['references']} references, {out['config']} ({out['config_digest']}), "
        f"{out['queries']} queries; read on demand: {', '.join(out['on_demand'])}"
    )
    for name in ("cold", "warm"):
        r = out[name]
        print(
            f"  {name}: hierarchy p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms; "
            f"per query {r['rows_per_query']:.0f} rows, {r['kib_per_query']:.0f} KiB read"
        )
    if args.json:
        write_record(args.json, out, args, config=reader.config)
    return out


if __name__ == "__main__":
    main()
