"""OLO alone on Nordland summer -> winter, on every N-th query (its whole-database curve over
all 3576 queries is 12.8 M comparisons, about an hour on 2 cores).

    python -m bench.olo_nordland [--every 10] [--tolerance 2] [--json F]

Uses the feature cache (the default OLO features, fitted on the summer references).
"""

from __future__ import annotations

import ast
import sys
import time

import numpy as np

from bench.harness import add_json, parser, write_record
from hmpf.datasets import dataset_root, frame_ground_truth, list_images
from hmpf.evaluation.evaluate import recall_at_n
from hmpf.features import FeatureCache, default_cache_dir, extract_images, fit_methods
from hmpf.methods import create_method


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--tolerance", type=int, default=2)
    ap.add_argument("--params", default="{}", help="OLO parameters as a Python dict literal")
    add_json(ap)
    args = ap.parse_args()
    olo = create_method("olo", ast.literal_eval(args.params))
    root = dataset_root() / "nordland_64x32"
    refs, qrys = list_images(root / "summer"), list_images(root / "winter")
    cache = FeatureCache(default_cache_dir())
    fit_methods({"olo": olo}, refs, cache=cache)
    picked = list(range(0, len(qrys), args.every))
    db = olo.stack(extract_images(refs, {"olo": olo}, cache=cache).features["olo"])
    qf = extract_images([qrys[i] for i in picked], {"olo": olo}, cache=cache).features["olo"]
    gt = frame_ground_truth(len(qrys), len(refs), args.tolerance)[picked]
    t = time.perf_counter()
    scores = np.stack([olo.scores(q, db) for q in qf])
    per = (time.perf_counter() - t) * 1e3 / scores.size
    rec = recall_at_n(scores, gt, higher_is_better=True)
    print(
        f"OLO {olo.config.model_dump(exclude_defaults=True)} on Nordland summer -> winter, "
        f"{len(picked)} queries (every {args.every}th) x {len(refs)} references, "
        f"+-{args.tolerance} frames: " + ", ".join(f"R@{k} {v:.3f}" for k, v in rec.items())
    )
    print(f"{per:.3f} ms per comparison")
    if args.json:
        results = {
            "olo": olo.config.model_dump(exclude_defaults=True),
            "every": args.every,
            "queries": len(picked),
            "references": len(refs),
            "tolerance": args.tolerance,
            "recall_at": {str(k): float(v) for k, v in rec.items()},
            "ms_per_comparison": per,
        }
        print(f"report: {write_record(args.json, results, args)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
