"""Speed figures behind the speed targets (medians, on this machine).

    python -m bench.speed [--json F]

* KAZE matching per candidate pair on real Gardens Point features (night query vs day
  references), with the default keypoint cap and without it, plus a bare vectorised
  1100 x 1100 match of unit descriptors for scale;
* extraction per image per method (single process, one image at a time);
* the hierarchy over a whole Gardens Point protocol (200 x 200), extraction included, from
  a cold cache, with the default number of worker processes.

With ``--json`` writes the figures too.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, machine, parser, timed, write_record
from hmpf.config import load_config
from hmpf.datasets import dataset_root, frame_ground_truth, list_images
from hmpf.evaluation.evaluate import EvalData, evaluate
from hmpf.features import FeatureCache
from hmpf.imageio import load_image
from hmpf.methods import create_method
from hmpf.methods.kaze import best_two_ssd, unit_rows


def main() -> int:
    ap = parser(__doc__)
    add_json(ap)
    args = ap.parse_args()
    gp = dataset_root() / "gardens_point"
    day = list_images(gp / "day_right")
    night = list_images(gp / "night_right")
    print(f"Machine: {machine()}\n")

    # -- KAZE matching per pair -------------------------------------------------------------
    kaze_match: list[dict[str, Any]] = []
    for cap in (500, None):
        kaze = create_method("kaze", {"max_keypoints": cap})
        refs = [kaze.extract(load_image(p)) for p in day[::10]]  # 20 references
        query = kaze.extract(load_image(night[50]))
        ms = timed(lambda k=kaze, q=query, r=refs: k.scores(q, r), 15) / len(refs)
        n_ref = np.mean([len(r) for r in refs])
        print(
            f"KAZE match, cap={cap}: {ms:.3f} ms per pair "
            f"(query {len(query)} keypoints, references {n_ref:.0f} on average)"
        )
        kaze_match.append(
            {
                "cap": cap,
                "ms_per_pair": float(ms),
                "query_keypoints": len(query),
                "ref_keypoints_mean": float(n_ref),
            }
        )
    rng = np.random.default_rng(0)
    a = unit_rows(rng.standard_normal((1100, 64)))
    b = unit_rows(rng.standard_normal((1100, 64)))
    bare_ms = timed(lambda: best_two_ssd(a, b), 15)
    print(f"bare 1100 x 1100 best-two SSD: {bare_ms:.3f} ms\n")

    # -- extraction per image ------------------------------------------------------------------
    images = [load_image(p) for p in day[:20]]
    extract_ms: dict[str, float] = {}
    for name in ("hog", "gist", "sad", "kaze"):
        m = create_method(name)
        per = statistics.median(timed(lambda m=m, im=im: m.extract(im), 3) for im in images)
        print(f"extract {name:5s}: {per:6.1f} ms per 960x540 image")
        extract_ms[name] = float(per)
    thumbs = [load_image(p) for p in list_images(dataset_root() / "nordland_64x32" / "summer")[:20]]
    gist = create_method("gist")
    thumb_ms = statistics.median(timed(lambda im=im: gist.extract(im), 3) for im in thumbs)
    print(f"extract gist : {thumb_ms:6.1f} ms per 64x32 Nordland thumbnail\n")

    # -- whole protocol, cold cache ----------------------------------------------------------------
    config = load_config(ROOT / "configs" / "handcrafted.yaml")
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        rep = evaluate(
            config,
            EvalData(day, night, frame_ground_truth(200, 200, 2), "+-2"),
            cache=FeatureCache(tmp),
            skip_curves=list(config.method_ids),
        )
        total = time.perf_counter() - t
    w = rep["wall_s"]
    print(
        f"handcrafted hierarchy, day_right -> night_right, cold cache: extraction "
        f"{w['extraction']:.1f} s + hierarchy {w['hierarchy']:.1f} s = "
        f"{w['extraction_plus_hierarchy']:.1f} s (whole call {total:.1f} s); "
        f"Combined recall@1 {rep['hierarchy']['combined_recall_at_1']:.3f}"
    )
    print(
        "per query (median ms): "
        + ", ".join(
            f"tier {i + 1} {v:.2f}" for i, v in enumerate(rep["timing_ms"]["tiers_per_query"])
        )
    )
    if args.json:
        results = {
            "kaze_match": kaze_match,
            "bare_best_two_ms": float(bare_ms),
            "extract_ms": extract_ms,
            "gist_thumbnail_ms": float(thumb_ms),
            "protocol": {
                "config": "handcrafted",
                "route": "gp_dr_nr",
                "extraction_s": float(w["extraction"]),
                "hierarchy_s": float(w["hierarchy"]),
                "total_s": float(w["extraction_plus_hierarchy"]),
                "whole_call_s": total,
                "combined_recall_at_1": float(rep["hierarchy"]["combined_recall_at_1"]),
                "tiers_per_query_ms": [float(v) for v in rep["timing_ms"]["tiers_per_query"]],
            },
        }
        print(f"report: {write_record(args.json, results, args)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
