"""End-to-end query time of hierarchy configs on one thread (the default's 100 ms budget).

    python bench/default_query.py [default-lite0 default ...] [--images 20] [--rounds 2]

For each config (preset name or YAML; ``default-lite0`` and ``default`` when none given):
decode + extraction + hierarchy against the 200 Gardens Point day_right references, one
night_right query at a time on one compute thread
(:func:`hmpf.evaluation.study.measure_query_ms`, median of ``--images`` queries after a
warm-up). The configs are timed in turn ``--rounds`` times (interleaved, so a change in the
machine's load touches every config alike); the table gives each config's median over its
rounds. Run it with nothing else on the machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hmpf.config import load_config  # noqa: E402
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root  # noqa: E402
from hmpf.evaluation.evaluate import EvalData  # noqa: E402
from hmpf.evaluation.study import ScoreBank, measure_query_ms  # noqa: E402
from hmpf.features import FeatureCache, default_cache_dir  # noqa: E402
from hmpf.runtime import machine_description, set_cnn_runtime  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("configs", nargs="*", default=["default-lite0", "default"])
    ap.add_argument("--images", type=int, default=20, help="queries timed per round")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds per config")
    ap.add_argument("--cache-dir", default=str(default_cache_dir()))
    args = ap.parse_args()
    set_cnn_runtime("onnx")
    print(f"Machine: {machine_description()}; load {os.getloadavg()[0]:.1f}", flush=True)
    ref, query = GARDENS_POINT_PROTOCOLS["gp_dr_nr"]
    data = EvalData.frames(dataset_root() / ref, dataset_root() / query, 2)
    cache = FeatureCache(args.cache_dir)
    banks = {}
    for c in args.configs:
        cfg = load_config(c)
        banks[c] = (cfg, ScoreBank.build(cfg, data, cache=cache))
    runs: dict[str, list[dict[str, float]]] = {c: [] for c in args.configs}
    for _ in range(args.rounds):
        for c, (cfg, bank) in banks.items():
            runs[c].append(measure_query_ms(cfg, bank, images=args.images, threads=1))
    print("\n| config | end to end (ms) | extraction | hierarchy | per round |")
    print("|---|---:|---:|---:|---|")
    for c, rs in runs.items():
        med = {
            k: statistics.median(float(r[k]) for r in rs)
            for k in ("total_ms", "extract_ms", "hierarchy_ms")
        }
        rounds = " / ".join(f"{r['total_ms']:.1f}" for r in rs)
        print(
            f"| {c} | {med['total_ms']:.1f} | {med['extract_ms']:.1f} | {med['hierarchy_ms']:.1f} "
            f"| {rounds} |"
        )
    print(f"\nload at end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
