"""Choose between hierarchy configs on training parts, report test parts: the default's rule.

    python -m bench.choose_default default path/to/variant.yaml ... [--nordland] [--out F]

For every config (a preset name or a YAML file; the first is the baseline):

* recall@1 (+-2 frames) of the hierarchy on the training and the test part of every Gardens
  Point protocol (``split_data``: alternating stretches of 20 frames, each part its own map,
  so fitted parameters are fitted on that part's references), and with ``--nordland`` on
  Nordland summer -> winter's parts too; and on the whole Gardens Point protocols;
* the query's extraction on one compute thread (median over ``--images`` day_right images);
* the bytes an index stores per reference (``exact`` precision, from the method's features).

Choice rule (training parts only): the config with the best mean training
recall over the protocols (with ``--budget-ms``: among those whose measured query stays
within it; measure on a quiet machine). Its test recall
is then compared with the baseline's by an exact paired sign test on the pooled test queries.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import add_cache_dir, add_json, machine, parser, write_record
from bench.one_pass import correct_flags, passes, query_ms
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root, list_images
from hmpf.evaluation.calibrate import paired_test
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import split_data
from hmpf.features import FeatureCache
from hmpf.imageio import load_image
from hmpf.runtime import set_cnn_runtime

NORDLAND = ("nordland_64x32/summer", "nordland_64x32/winter")


def load_protocols(
    nordland: bool = False, nordland_block: int = 20
) -> tuple[dict[str, EvalData], dict[str, tuple[EvalData, EvalData]]]:
    """The Gardens Point protocols (and Nordland summer -> winter), whole and ``blocks``-split
    (20 frames; Nordland's stretch ``nordland_block``): (whole, (training, test) parts)."""
    root = dataset_root()
    protocols = dict(GARDENS_POINT_PROTOCOLS)
    if nordland:
        protocols["nordland_s_w"] = NORDLAND
    full = {n: EvalData.frames(root / r, root / q, 2) for n, (r, q) in protocols.items()}
    parts = {
        n: split_data(d, block=nordland_block if n not in GARDENS_POINT_PROTOCOLS else 20)
        for n, d in full.items()
    }
    return full, parts


def timing_images(n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` day_right images timed (evenly spaced) and the images methods are fitted on for
    timing (every 7th day_right frame)."""
    refs = list_images(dataset_root() / "gardens_point" / "day_right")
    pick = np.linspace(0, len(refs) - 1, n).round().astype(int)
    return [load_image(refs[i]) for i in pick], [load_image(p) for p in refs[::7]]


def measure(
    config: HierarchyConfig,
    full: dict[str, EvalData],
    parts: dict[str, tuple[EvalData, EvalData]],
    cache: FeatureCache,
    timing: tuple[list[np.ndarray], list[np.ndarray]] | None,
    *,
    protocols: list[str] | None = None,
    whole: bool = True,
) -> tuple[dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """One config's row: passes, ``query_ms`` (with ``timing`` = (timed, fitting) images),
    recall@1 per protocol on the training and test parts (and with ``whole`` the whole Gardens
    Point protocols), their means and the pooled correct flags; and the flags per part and
    protocol. ``protocols``: those of ``parts`` to evaluate (default all)."""
    names = list(parts) if protocols is None else protocols
    row: dict[str, Any] = {"passes": passes(config)}
    if timing is not None:
        row["query_ms"] = query_ms(config, *timing)
    by_part: dict[str, dict[str, np.ndarray]] = {}
    for i, part in enumerate(("train", "test", "whole") if whole else ("train", "test")):
        flags = {
            p: correct_flags(config, parts[p][i] if part != "whole" else full[p], cache)
            for p in names
            if part != "whole" or p in GARDENS_POINT_PROTOCOLS
        }
        row[part] = {p: float(f.mean()) for p, f in flags.items()}
        row[f"{part}_mean"] = float(np.mean(list(row[part].values())))
        row[f"{part}_flags"] = np.concatenate(list(flags.values())).tolist()
        by_part[part] = flags
    return row, by_part


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("configs", nargs="+", help="preset names or YAML files; first = baseline")
    ap.add_argument("--nordland", action="store_true", help="Nordland summer -> winter too")
    ap.add_argument("--images", type=int, default=10, help="images timed (day_right)")
    ap.add_argument(
        "--budget-ms",
        type=float,
        default=None,
        help="only configs whose measured query ms is within this (off by default: on a "
        "shared machine the timings are not the quiet ones the budget is stated in)",
    )
    add_cache_dir(ap)
    add_json(ap, "--out", type=Path, help="write the figures as JSON")
    args = ap.parse_args()
    set_cnn_runtime("onnx")
    print(f"Machine: {machine()}", flush=True)
    timing = timing_images(args.images)
    cache = FeatureCache(args.cache_dir)
    full, parts = load_protocols(args.nordland)
    protocols = list(parts)
    out: dict[str, Any] = {}
    for name in args.configs:
        config: HierarchyConfig = load_config(name)
        row, _ = measure(config, full, parts, cache, timing)
        out[name] = row
        print(
            f"{name}: {row['query_ms']:.1f} ms/query, train {row['train_mean']:.3f}, "
            f"test {row['test_mean']:.3f}, GP whole {row['whole_mean']:.3f}",
            flush=True,
        )
    names = list(protocols)
    print(
        "\nrecall@1 (+-2); query extraction on one thread (median); p: paired sign test, pooled\n"
    )
    print(f"| config | ms | train: {' / '.join(names)} (mean) | test (mean) | test vs first |")
    print("|---|---:|---|---|---|")
    base = out[args.configs[0]]
    for name, row in out.items():
        tr = " / ".join(f"{row['train'][p]:.3f}" for p in names)
        te = " / ".join(f"{row['test'][p]:.3f}" for p in names)
        t = paired_test(np.array(row["test_flags"]), np.array(base["test_flags"]))
        print(
            f"| {name} | {row['query_ms']:.1f} | {tr} ({row['train_mean']:.3f}) | {te} "
            f"({row['test_mean']:.3f}) | {t['wins']}/{t['losses']}, p = {t['p']:.3f} |"
        )
    ok = [n for n in out if args.budget_ms is None or out[n]["query_ms"] <= args.budget_ms]
    if ok:
        chosen = max(ok, key=lambda n: out[n]["train_mean"])
        t = paired_test(np.array(out[chosen]["test_flags"]), np.array(base["test_flags"]))
        print(
            f"\nChosen on the training parts: {chosen} (train {out[chosen]['train_mean']:.3f} "
            f"vs {base['train_mean']:.3f}); test {out[chosen]['test_mean']:.3f} vs "
            f"{base['test_mean']:.3f}: {t['wins']} wins / {t['losses']} losses, p = {t['p']:.3f}"
        )
    if args.out:
        # the provenance beside the configs' rows (bench/pages.py keeps the rows: dicts with "test")
        write_record(args.out, out, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
