"""Build throughput and bytes on disk per reference for ``hmpf-index build``.

    .venv/bin/python -m bench.index_build --config configs/handcrafted.yaml \\
        --images ../shared/datasets/gardens_point/day_right [--limit 200] [--workers 2]

Builds into a fresh temporary folder (no feature cache, so every image is extracted), then
prints images/s and bytes on disk per reference (per method and in total); with ``--json``
writes them too. The build stores the map prior when the config's acceptance models read it
(the ``default`` preset's, since 2026-11-29), which extracts its pseudo-queries and references
again: its seconds are printed apart (``map_prior_s``, part of the build's);
``--no-map-prior`` builds without it. The CNN runtime is the process's
(``HMPF_CNN_RUNTIME``). A replica's memory per reference is measured by ``python -m
bench.capacity`` on two indexes of different sizes (in the building process the allocator
reuses the build's freed pages, so a reader opened there shows no growth).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from bench.harness import add_json, parser, write_record
from hmpf.datasets import list_images
from hmpf.index import layout
from hmpf.runtime import cnn_runtime
from indexer.build import BuildOptions, build


def main() -> None:
    p = parser(__doc__)
    p.add_argument("--config", required=True)
    p.add_argument("--images", required=True)
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--precision", default="exact", choices=["exact", "compact"])
    p.add_argument(
        "--map-prior",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="store the map prior (default: when the config's models read it)",
    )
    add_json(p)
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "images"
        folder.mkdir()
        paths = list_images(a.images)[: a.limit]
        for src in paths:
            (folder / src.name).symlink_to(src.resolve())
        opts = BuildOptions(workers=a.workers, progress=False, precision=a.precision)
        s = build(a.config, folder, Path(tmp) / "index", options=opts, with_map_prior=a.map_prior)
        n = s.images
        entry = layout.read_manifest(Path(tmp) / "index" / s.version).get("map_prior") or {}
        prior_s = entry.get("seconds")
        print(
            f"config {a.config}, {n} images from {a.images} ({a.precision}), "
            f"{os.cpu_count()} CPUs, workers {a.workers or os.cpu_count()}"
        )
        print(
            f"build: {s.seconds:.1f} s, {s.images_per_s:.1f} images/s (end to end: hashing, "
            "extraction, HDF5, FAISS, fsync)"
        )
        if entry:
            print(
                f"of which the map prior: {prior_s or 0:.1f} s ({entry.get('pseudo_queries')} "
                f"pseudo-queries, map_prior {entry.get('map_prior')})"
            )
        print(
            f"on disk: {(s.bytes_total - s.bytes_models) / n / 1024:.1f} KiB per reference "
            f"({s.bytes_total / 1e6:.2f} MB in all, of which CNN models "
            f"{s.bytes_models / 1e6:.2f} MB, once per version)"
        )
        for mid, b in s.bytes_per_method.items():
            print(f"  {mid:<8} {b / n / 1024:8.2f} KiB per reference")
        print(f"  {'thumbs':<8} {s.bytes_thumbnails / n / 1024:8.2f} KiB per reference")
        if a.json:
            results = {
                "cnn_runtime": cnn_runtime(),
                "images": n,
                "seconds": s.seconds,
                "images_per_s": s.images_per_s,
                "bytes_per_reference": s.bytes_total / n,
                # the CNN models a version carries are stored once, whatever its size
                "bytes_models": s.bytes_models,
                "bytes_per_reference_without_models": (s.bytes_total - s.bytes_models) / n,
                "bytes_per_reference_by_method": {m: b / n for m, b in s.bytes_per_method.items()},
                "bytes_per_reference_thumbnails": s.bytes_thumbnails / n,
                # the map prior's part of ``seconds`` (None: not stored)
                "map_prior_s": prior_s,
                "map_prior": entry.get("map_prior"),
                "pseudo_queries": entry.get("pseudo_queries"),
            }
            write_record(a.json, results, a, config=a.config)


if __name__ == "__main__":
    main()
