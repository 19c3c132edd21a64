"""Where a single-frame query's time goes, by stage, on index versions of different sizes.

``python -m bench.scale_stages --index V1k V1M --json docs/experiments/scale/stages.json``
opens each version in this process as ``hmpf-serve`` does (:meth:`service.engine.Loaded.open`,
one compute thread), runs the service's query path (:func:`service.engine.run_query`, then
:func:`service.answer.localize_response`) for ``--frames`` Gardens Point night_right frames,
twice (the first round warms the caches and is not counted), and prints per version the
median over the frames of each stage's wall time in ms:

* ``extract``: the query's features (CNN passes, Gist);
* ``faiss``: FAISS's searches of tier 1 (:meth:`hmpf.index.reader.IndexReader.search`, every
  approximate method);
* ``rescore``: the rest of an approximate tier 1 (:meth:`IndexReader._approx_scores`): the
  fixed sample and FAISS's candidates scored exactly, the candidates' rows read from disk,
  the whole-map array filled;
* ``tier1_passes``: tier 1's time minus the two above: min-max normalisation and top-k over
  the whole map;
* ``later_tiers``, ``fusion``, ``answer`` (the response, with the acceptance decision).

It does not go through HTTP (``bench/scale.py measure`` times the real server): it says
which stage grows with the map, not what a client waits.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import machine, provenance, write_json
from hmpf.datasets import dataset_root, list_images
from hmpf.index.reader import IndexReader

STAGES = (
    "extract",
    "faiss",
    "rescore",
    "tier1_passes",
    "later_tiers",
    "fusion",
    "answer",
    "hierarchy",
)


class _Clock:
    """Wall time spent in :meth:`IndexReader.search` and :meth:`IndexReader._approx_scores`
    (which calls the former), summed until :meth:`reset`."""

    def __init__(self) -> None:
        self.search = 0.0
        self.approx = 0.0
        self._search = IndexReader.search
        self._approx = IndexReader._approx_scores

    def install(self) -> None:
        IndexReader.search = self._timed(self._search, "search")  # type: ignore[method-assign]
        IndexReader._approx_scores = self._timed(self._approx, "approx")  # type: ignore[method-assign]

    def _timed(self, fn: Any, key: str) -> Any:
        def timed(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                setattr(self, key, getattr(self, key) + time.perf_counter() - t)

        return timed

    def uninstall(self) -> None:
        IndexReader.search = self._search  # type: ignore[method-assign]
        IndexReader._approx_scores = self._approx  # type: ignore[method-assign]

    def reset(self) -> None:
        self.search = self.approx = 0.0


def measure(
    index: Path,
    frames: Sequence[Path],
    rounds: int = 2,
    approx_k: int | None = None,
    params: str = "",
) -> dict[str, Any]:
    """Median stage times (ms) of ``frames`` against ``index``; the last of ``rounds``
    rounds counts. ``params``: FAISS search parameters for every approximate tier-1
    method (e.g. ``k_factor_front=2``), on top of the version's own."""
    from hmpf.api import LocalizeParams
    from hmpf.index.ann import faiss_module
    from hmpf.runtime import set_compute_threads
    from service.answer import localize_response
    from service.engine import Loaded, run_query
    from service.images import decode_upload

    set_compute_threads(1)
    faiss_module().omp_set_num_threads(1)  # as hmpf-serve caps FAISS's OpenMP pool
    clock = _Clock()
    clock.install()
    loaded = Loaded.open(index, None, verify="stamp", approx_k=approx_k)
    try:
        reader = loaded.reader
        approximate = reader.approximate_methods()
        reader.set_faiss_params({"*": params})
        images = [decode_upload(p.read_bytes(), max_pixels=1 << 30, source=p.name) for p in frames]
        localize = LocalizeParams()
        rows: list[dict[str, float]] = []
        matches: list[int] = []
        with ThreadPoolExecutor(1) as pool:
            for r in range(rounds):
                for image in images:
                    clock.reset()
                    timing: dict[str, Any] = {}
                    result, allowed = run_query(loaded, image, None, timing, pool)
                    t = time.perf_counter()
                    answer = localize_response(loaded, result, allowed, localize, timing)
                    answer_ms = (time.perf_counter() - t) * 1e3
                    if r < rounds - 1 or result is None:
                        continue
                    tiers = [tr.time_ms for tr in result.tiers]
                    rows.append(
                        {
                            "extract": timing["extract"],
                            "faiss": clock.search * 1e3,
                            "rescore": (clock.approx - clock.search) * 1e3,
                            "tier1_passes": tiers[0] - clock.approx * 1e3,
                            "later_tiers": float(sum(tiers[1:])),
                            "fusion": result.fusion_ms,
                            "answer": answer_ms,
                            "hierarchy": timing["hierarchy"],
                        }
                    )
                    matches.append(-1 if answer.match is None else answer.match.reference_id)
        n, rescored = reader.n, reader.approx_k
    finally:
        clock.uninstall()
        loaded.reader.close()
    return {
        "index": str(index),
        "references": n,
        "approximate_tier1": approximate,
        "faiss_params": params or None,
        "approx_k": rescored,
        "frames": len(rows),
        "p50_ms": {s: float(np.median([row[s] for row in rows])) for s in STAGES},
        "matches": matches,
    }


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--index",
        nargs="+",
        required=True,
        metavar="FOLDER[@PARAMS]",
        help="index folders; @PARAMS: FAISS search parameters for its approximate tier-1 "
        "methods (e.g. V1M@k_factor_front=2); a folder may come more than once",
    )
    p.add_argument("--queries", type=Path, default=None, help="default night_right")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--rounds", type=int, default=2, help="the last one counts")
    p.add_argument("--approx-k", type=int, default=None, help="rows re-scored (hmpf-serve's)")
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    if a.frames < 1 or a.rounds < 1 or (a.approx_k is not None and a.approx_k < 1):
        p.error("--frames, --rounds and --approx-k must be >= 1")
    qdir = a.queries or dataset_root() / "gardens_point" / "night_right"
    frames = list_images(qdir)[: a.frames]
    print(machine(), f"(load {os.getloadavg()[0]:.2f})")
    split = ((i, "", "") if "@" not in i else i.rpartition("@") for i in a.index)
    runs = [(Path(folder), params) for folder, _, params in split]
    versions = [measure(index, frames, a.rounds, a.approx_k, params) for index, params in runs]
    print("report: stage p50 in ms, one thread, in process (no HTTP)")
    print(f"{'references':>12} " + " ".join(f"{s:>12}" for s in STAGES) + "  FAISS params")
    for v in versions:
        print(
            f"{v['references']:>12,} "
            + " ".join(f"{v['p50_ms'][s]:>12.2f}" for s in STAGES)
            + f"  {v['faiss_params'] or '(stored)'}"
        )
    if a.json:
        with IndexReader(runs[0][0], verify=False) as reader:
            config = reader.config
        write_json(a.json, {**provenance(config.name, config, a), "versions": versions})
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
