"""Cost of the references' profile (hmpf.confidence.ReferenceProfile) against the map's size.

    python -m bench.profile_scale [--sizes 10000,100000,1000000] [--dim 1280] [--threads 2]

The profile is what the absolute confidence evidence (``ref_z``) compares a query's score
with: per reference and tier-1 global method, the mean and spread of the scores it gets
from a fixed sample of 256 unrelated references. The service builds it when it opens an
index version whose confidence model reads it (start and reload), ``hmpf-eval`` when it
applies such a model.

Synthetic map: N random float32 vectors of ``--dim`` dimensions (GeM on EfficientNet-Lite0
has 1280), L2-normalised, one route in file order, scored with the library's Euclidean
distance (what GeM and NetVLAD use). Prints per size the build time (best of
``--repeat``), the time per million references, and the profile's bytes (2 float64 per
reference and method).
"""

from __future__ import annotations

import time
from typing import ClassVar

import numpy as np

from bench.harness import machine, parser
from hmpf.confidence import ReferenceProfile
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
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    set_compute_threads(args.threads)
    method = _Vectors()
    print(f"machine: {machine()}; {args.threads} threads, dim {args.dim}")
    print(
        f"| references | build (s, best of {args.repeat}) | s per 1M references | profile bytes |"
    )
    print("|---|---|---|---|")
    rng = np.random.default_rng(0)
    for n in (int(s) for s in args.sizes.split(",")):
        db = np.empty((n, args.dim), dtype=np.float32)
        for lo in range(0, n, 65536):  # filled in chunks: no float64 copy of the whole map
            block = rng.standard_normal((min(n, lo + 65536) - lo, args.dim), dtype=np.float32)
            db[lo : lo + len(block)] = block / np.linalg.norm(block, axis=1, keepdims=True)
        routes = RouteMap.from_metadata(n)
        best = float("inf")
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            prof = ReferenceProfile.build({"v": method}, {"v": db}, ["v"], routes)
            best = min(best, time.perf_counter() - t0)
        nbytes = prof.mean.nbytes + prof.std.nbytes
        print(
            f"| {n:,} | {best:.2f} | {best / n * 1e6:.1f} | {nbytes / 2**20:.1f} MiB |", flush=True
        )
        del db, prof
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
