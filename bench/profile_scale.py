"""Cost of the references' profile (hmpf.confidence.ReferenceProfile) against the map's size:
building it, against storing it with an index version and reading it back.

    python -m bench.profile_scale [--sizes 10000,100000,1000000] [--dim 1280] [--threads 2] \\
        [--repeat 3] [--json F]

The profile is what the absolute confidence evidence (``ref_z``) compares a query's score
with: per reference and tier-1 global method, the mean and spread of the scores it gets
from a fixed sample of 256 unrelated references. An index version stores it
(``profile.h5``, computed when ``hmpf-index`` writes the version), so the service reads it
when it opens the version (start and reload); a version written before that, and
``hmpf-eval`` without an index, build it.

Synthetic map: N random float32 vectors of ``--dim`` dimensions (GeM on EfficientNet-Lite0
has 1280), L2-normalised, one route in file order, scored with the library's Euclidean
distance (what GeM and NetVLAD use). Prints per size the build time (median of
``--repeat``), the time per million references, the medians of ``--repeat`` writes
(:func:`hmpf.index.storage.write_profile`) and reads (:func:`~hmpf.index.storage.read_profile`,
page cache warm: the file was just written) after one warm-up each, the sha256 a reader
checks the file with when it opens the version, and the file's bytes (2 float64 per
reference and method); with ``--json`` writes them too.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from bench.harness import add_json, machine, parser, timed, write_record
from hmpf.confidence import ReferenceProfile, profile_params
from hmpf.index.layout import sha256_file
from hmpf.index.storage import read_profile, write_profile
from hmpf.methods.base import GlobalMethod, euclidean
from hmpf.runtime import set_compute_threads
from hmpf.sequence import RouteMap


class _Vectors(GlobalMethod):
    """Stored vectors scored by Euclidean distance (no extraction: the map is synthetic)."""

    name: ClassVar[str] = "vectors"
    higher_is_better: ClassVar[bool] = False

    def _extract(self, image: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--dim", type=int, default=1280)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    add_json(ap)
    args = ap.parse_args()
    set_compute_threads(args.threads)
    method = _Vectors()
    print(f"machine: {machine()}; {args.threads} threads, dim {args.dim}")
    print(
        f"| references | build (s, median of {args.repeat}) | s per 1M references "
        "| write profile.h5 (ms) | read profile.h5 (ms) | sha256 of it (ms) | file bytes |"
    )
    print("|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    folder = Path(tempfile.mkdtemp(prefix="profile_scale-"))
    path = folder / "profile.h5"
    sizes: list[dict[str, Any]] = []
    for n in (int(s) for s in args.sizes.split(",")):
        db = np.empty((n, args.dim), dtype=np.float32)
        for lo in range(0, n, 65536):  # filled in chunks: no float64 copy of the whole map
            block = rng.standard_normal((min(n, lo + 65536) - lo, args.dim), dtype=np.float32)
            db[lo : lo + len(block)] = block / np.linalg.norm(block, axis=1, keepdims=True)
        routes = RouteMap.from_metadata(n)
        runs = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            prof = ReferenceProfile.build({"v": method}, {"v": db}, ["v"], routes)
            runs.append(time.perf_counter() - t0)
        build_s = statistics.median(runs)
        write_ms = timed(partial(write_profile, path, prof, profile_params()), args.repeat)
        read_ms = timed(lambda: read_profile(path), args.repeat)
        back = read_profile(path)
        assert np.array_equal(back.mean, prof.mean, equal_nan=True)
        assert np.array_equal(back.std, prof.std, equal_nan=True)
        hash_ms = timed(lambda: sha256_file(path), args.repeat)
        file_bytes = path.stat().st_size
        print(
            f"| {n:,} | {build_s:.2f} | {build_s / n * 1e6:.1f} | {write_ms:.1f} | {read_ms:.1f} "
            f"| {hash_ms:.1f} | {file_bytes / 2**20:.1f} MiB |",
            flush=True,
        )
        # the table's columns and nothing else
        sizes.append(
            {
                "n": n,
                "build_s": build_s,
                "build_s_per_million_refs": build_s / n * 1e6,
                "write_ms": write_ms,
                "read_ms": read_ms,
                "sha256_ms": hash_ms,
                "file_bytes": file_bytes,
            }
        )
        del db, prof, back
    path.unlink(missing_ok=True)
    folder.rmdir()
    if args.json:
        results = {"dim": args.dim, "threads": args.threads, "repeat": args.repeat, "sizes": sizes}
        print(f"report: {write_record(args.json, results, args)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
