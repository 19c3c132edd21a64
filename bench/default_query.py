"""End-to-end query time of hierarchy configs on one thread (the default's 100 ms budget).

    python -m bench.default_query [default-lite0 default ...] [--images 20] [--rounds 2] [--json F]

For each config (preset name or YAML; ``default-lite0`` and ``default`` when none given):
decode + extraction + hierarchy against the 200 Gardens Point day_right references, one
night_right query at a time on one compute thread
(:func:`hmpf.evaluation.study.measure_query_ms`, median of ``--images`` queries after a
warm-up). The configs are timed in turn ``--rounds`` times (interleaved, so a change in the
machine's load touches every config alike); the table gives each config's median over its
rounds. Run it with nothing else on the machine.
"""

from __future__ import annotations

import os
import statistics
from typing import Any

from bench.harness import add_cache_dir, add_json, machine, parser, protocol_data, write_record
from hmpf.config import load_config
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import ScoreBank, measure_query_ms
from hmpf.features import FeatureCache
from hmpf.runtime import set_cnn_runtime

KEYS = ("total_ms", "extract_ms", "hierarchy_ms")


def interleaved(
    configs: list[str], data: EvalData, cache: FeatureCache, images: int, rounds: int
) -> dict[str, list[dict[str, float]]]:
    """Config -> its ``rounds`` timings, the configs timed in turn each round."""
    banks = {}
    for c in configs:
        cfg = load_config(c)
        banks[c] = (cfg, ScoreBank.build(cfg, data, cache=cache))
    runs: dict[str, list[dict[str, float]]] = {c: [] for c in configs}
    for _ in range(rounds):
        for c, (cfg, bank) in banks.items():
            runs[c].append(measure_query_ms(cfg, bank, images=images, threads=1))
    return runs


def medians(runs: dict[str, list[dict[str, float]]]) -> dict[str, dict[str, Any]]:
    """Config -> the median over its rounds of each figure, and the rounds' totals."""
    return {
        c: {
            **{k: statistics.median(float(r[k]) for r in rs) for k in KEYS},
            "rounds_total_ms": [float(r["total_ms"]) for r in rs],
        }
        for c, rs in runs.items()
    }


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("configs", nargs="*", default=["default-lite0", "default"])
    ap.add_argument("--images", type=int, default=20, help="queries timed per round")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds per config")
    add_cache_dir(ap)
    add_json(ap)
    ap.smoke(configs=["default-lite0"], images=3, rounds=1)
    args = ap.parse_args()
    set_cnn_runtime("onnx")
    print(f"Machine: {machine()}; load {os.getloadavg()[0]:.1f}", flush=True)
    data = protocol_data("gp_dr_nr")
    runs = interleaved(args.configs, data, FeatureCache(args.cache_dir), args.images, args.rounds)
    table = medians(runs)
    print("\n| config | end to end (ms) | extraction | hierarchy | per round |")
    print("|---|---:|---:|---:|---|")
    for c, med in table.items():
        rounds = " / ".join(f"{t:.1f}" for t in med["rounds_total_ms"])
        print(
            f"| {c} | {med['total_ms']:.1f} | {med['extract_ms']:.1f} | {med['hierarchy_ms']:.1f} "
            f"| {rounds} |"
        )
    print(f"\nload at end {os.getloadavg()[0]:.1f}")
    if args.json:
        write_record(args.json, {"configs": table}, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
