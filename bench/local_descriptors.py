"""Learned binary local descriptors (BEBLID / TEBLID) against KAZE's, Gardens Point.

    python -m bench.local_descriptors [--json out.json] [--time-images 10] [--descriptors a,b]
    python -m bench.local_descriptors --time-only [--json F]    (extraction and matching)
    python -m bench.local_descriptors --control 20,0.8 [--json F]   (KAZE re-matched)

KAZE keypoints (the method's detection, orientation and 500 strongest) described by KAZE's
64 floats (the baseline), BEBLID (512 bits), TEBLID (256 and 512 bits) or ORB (256 bits),
matched with KAZE's rule (``hmpf.methods.kaze``). Per Gardens Point protocol (+-2 frames,
``blocks`` split), on the training and the test part:

* matching choice (TRAINING parts only): for each binary descriptor, ``match_threshold`` x
  ``max_ratio`` from a small grid, chosen on the mean training recall@1 of ``kaze`` alone
  (KAZE's descriptor keeps its defaults, the baseline; ``kaze_tuned``, KAZE's descriptor with
  its own grid choice, is the control);
* ``kaze`` alone over the whole database; the ``handcrafted`` preset with its ``kaze``
  replaced; the ``default`` preset with that ``kaze`` added to the final tier; ``inliers``
  (its defaults plus the descriptor and the chosen matching) added to the default's final
  tier (scored on the candidates of the default's tier 1 only, as the service would).

Each family's rival is chosen on the training means and reported on the test parts with a
paired sign test against the same structure with KAZE's descriptor
(:func:`hmpf.evaluation.calibrate.paired_test`); ms per query end to end on one thread
(:func:`hmpf.evaluation.study.measure_query_ms`, first test part); bytes per reference as an
index stores them (``exact`` precision). Nearest-two Hamming / SSD values are computed once
per (descriptor, query, reference) and the grid's distances from them; the chosen settings'
matrices are checked against ``Kaze.scores`` on a few queries.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import (
    add_data,
    add_json,
    machine,
    parser,
    split_parts,
    write_record,
)
from bench.inliers import bytes_per_reference
from hmpf.config import HierarchyConfig, TierConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS as PROTOCOLS
from hmpf.evaluation.calibrate import paired_test
from hmpf.evaluation.evaluate import prepare
from hmpf.evaluation.study import ScoreBank, measure_query_ms
from hmpf.features import FeatureCache
from hmpf.methods import Method, create_method
from hmpf.methods.kaze import match_distance, nearest_two_any

#: Descriptor settings compared (label -> kaze options); "kaze" is the baseline.
DESCRIPTORS: dict[str, dict[str, Any]] = {
    "kaze": {},
    # KAZE's descriptor with the matching chosen on the same grid (a control: how much of a
    # binary descriptor's gain is its matching setting's)
    "kaze_tuned": {},
    "beblid": {"descriptor": "beblid"},
    "teblid": {"descriptor": "teblid"},
    "teblid512": {"descriptor": "teblid", "descriptor_bits": 512},
    "orb": {"descriptor": "orb"},
}
#: Matching grid for the binary descriptors (match_threshold %, max_ratio).
GRID = [(t, r) for t in (20.0, 25.0, 30.0) for r in (0.7, 0.8, 0.9)]
INLIER_DESCRIPTORS = ("kaze", "kaze_tuned", "beblid", "teblid")


def pool_config(presets: tuple[str, ...] = ("default", "handcrafted")) -> HierarchyConfig:
    """Every method of ``presets``, in one tier (a score pool)."""
    methods: dict[str, dict[str, Any]] = {}
    ids: set[str] = set()
    for name in presets:
        cfg = load_config(name)
        methods.update({m: dict(p) for m, p in cfg.methods.items()})
        ids |= set(cfg.method_ids)
    return HierarchyConfig(
        name="pool", methods=methods, tiers=[TierConfig(methods=sorted(ids), k=1)], weights=[1.0]
    )


def with_kaze(base: HierarchyConfig, kid: str, params: dict[str, Any], tiers: Any) -> Any:
    """``base`` with method id ``kid`` (a ``kaze`` / ``inliers`` with ``params``) and tiers."""
    used = {m for ms, _ in tiers for m in ms}
    methods = {m: dict(p) for m, p in base.methods.items() if m in used}
    methods[kid] = dict(params)
    return HierarchyConfig(
        name=kid,
        mode=base.mode,
        tier_score=base.tier_score,
        methods=methods,
        tiers=[TierConfig(methods=list(ms), k=k) for ms, k in tiers],
        weights=base.weights,
    )


def families(desc: str, params: dict[str, Any], with_default: bool) -> dict[str, HierarchyConfig]:
    """The structures each descriptor is measured in (family -> config)."""
    d, h = load_config("default"), load_config("handcrafted")
    kid, iid = f"kaze_{desc}", f"inliers_{desc}"
    kp = {"type": "kaze", **params}
    swap = [(tuple(kid if m == "kaze" else m for m in t.methods), t.k) for t in h.tiers]
    d_final = [(tuple(d.tiers[0].methods), d.tiers[0].k), ((*d.tiers[1].methods, kid), 1)]
    i_final = [(tuple(d.tiers[0].methods), d.tiers[0].k), ((*d.tiers[1].methods, iid), 1)]
    out = {
        "kaze alone": HierarchyConfig(
            name=kid, methods={kid: kp}, tiers=[TierConfig(methods=[kid], k=1)]
        ),
        "handcrafted, kaze swapped": with_kaze(h, kid, kp, swap),
        "default + kaze in final tier": with_kaze(d, kid, kp, d_final),
    }
    if not with_default:
        return {k: v for k, v in out.items() if not k.startswith("default")}
    if desc in INLIER_DESCRIPTORS:
        out["default + inliers in final tier"] = with_kaze(
            d, iid, {"type": "inliers", **params}, i_final
        )
    return out


def grid_matrices(qs: list[Any], db: Any) -> tuple[dict[tuple[float, float], np.ndarray], float]:
    """Distances (nq, nd) of every query to every reference for each GRID setting (from one
    nearest-two pass per pair), and ms per pair of that pass."""
    nq, nd = len(qs), len(db)
    out = {g: np.empty((nq, nd)) for g in GRID}
    spent = 0.0
    for qi, q in enumerate(qs):
        n = len(q)
        s1, s2 = np.full((nd, n), np.inf), np.full((nd, n), np.inf)
        t0 = time.perf_counter()
        for ri in range(nd):
            s1[ri], s2[ri], _ = nearest_two_any(q.descriptors, db[ri].descriptors)
        spent += time.perf_counter() - t0
        for t, r in GRID:
            out[t, r][qi] = match_distance(s1, s2, match_threshold=t, max_ratio=r)
    return out, spent * 1e3 / max(1, nq * nd)


def sparse_inliers(bank: ScoreBank, m: Method, feats: tuple[Any, list[Any]]) -> np.ndarray:
    """``m``'s scores on the candidates the default's tier 1 passes on (NaN elsewhere)."""
    inputs = [res.tiers[1].inputs for res in bank.results(load_config("default"))]
    db, qs = feats
    mat = np.full((bank.n_query, bank.n_db), np.nan)
    for qi, (q, c) in enumerate(zip(qs, inputs, strict=True)):
        u = np.unique(np.asarray(c, np.int64))
        mat[qi, u] = m.scores(q, db, u)
    return mat


def time_descriptors(datasets: Path, n_query: int = 10) -> dict[str, dict[str, float]]:
    """Extraction and ``Kaze.scores`` (against 100 day_right references) per descriptor, one
    thread, medians over ``n_query`` night_right queries; printed and returned by descriptor."""
    from hmpf.datasets import list_images
    from hmpf.imageio import load_image
    from hmpf.runtime import set_compute_threads

    set_compute_threads(1)
    gp = datasets / "gardens_point"
    refs = [load_image(p) for p in list_images(gp / "day_right")[::2]]
    queries = [load_image(p) for p in list_images(gp / "night_right")[1 :: 200 // n_query]]
    out: dict[str, dict[str, float]] = {}
    for name, p in DESCRIPTORS.items():
        m = create_method("kaze", p)
        db = m.stack([m.extract(r) for r in refs])
        ext, score = [], []
        for img in queries:
            t0 = time.perf_counter()
            q = m.extract(img)
            t1 = time.perf_counter()
            m.scores(q, db)
            ext.append((t1 - t0) * 1e3)
            score.append((time.perf_counter() - t1) * 1e3)
        out[name] = {
            "extract_ms": float(np.median(ext)),
            "scores_ms": float(np.median(score)),
            "references": len(refs),
            "queries": len(queries),
            "keypoints_per_reference": float(np.mean(db.counts)),
        }
        print(
            f"{name}: extract {out[name]['extract_ms']:.1f} ms, scores vs {len(refs)} references "
            f"{out[name]['scores_ms']:.1f} ms, {out[name]['keypoints_per_reference']:.0f} "
            "keypoints per reference",
            flush=True,
        )
    return out


def control(
    datasets: Path, cache: FeatureCache, matching: dict[str, Any]
) -> dict[str, dict[str, dict[str, Any]]]:
    """KAZE's descriptor with other matching (``matching``): alone and in the handcrafted
    preset, against KAZE's defaults, per protocol and part (no grid, no timing); printed and
    returned as ``{protocol: {part: {structure: {"base", "tuned", "wins", "losses", "p"}}}}``."""
    h = load_config("handcrafted")
    tuned = create_method("kaze", matching)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for proto in PROTOCOLS:
        for part, split in split_parts(proto, datasets):
            bank = ScoreBank.build(h, split, cache=cache)
            db, qs = bank.features["kaze"]
            bank.methods["tuned"] = tuned
            bank.scores["tuned"] = np.stack([np.asarray(tuned.scores(x, db)) for x in qs])
            swap = [(tuple("tuned" if m == "kaze" else m for m in t.methods), t.k) for t in h.tiers]
            tuned_h = with_kaze(h, "tuned", {"type": "kaze", **matching}, swap)
            alone = np.asarray(bank.gt[np.arange(bank.n_query), bank.scores["kaze"].argmin(1)])
            alone_t = np.asarray(bank.gt[np.arange(bank.n_query), bank.scores["tuned"].argmin(1)])
            hc, hc_t = (np.asarray(bank.run(c).correct, bool) for c in (h, tuned_h))
            cell = {}
            for name, base, new in (("alone", alone, alone_t), ("handcrafted", hc, hc_t)):
                t = paired_test(new, base)
                cell[name] = {
                    "base": float(base.mean()),
                    "tuned": float(new.mean()),
                    "wins": int(t["wins"]),
                    "losses": int(t["losses"]),
                    "p": float(t["p"]),
                }
            out.setdefault(proto, {})[part] = cell
            a, b = cell["alone"], cell["handcrafted"]
            print(
                f"{proto} {part}: alone {a['base']:.3f} -> {a['tuned']:.3f} "
                f"(+{a['wins']}/-{a['losses']}, p {a['p']:.2g}); handcrafted {b['base']:.3f} -> "
                f"{b['tuned']:.3f} (+{b['wins']}/-{b['losses']}, p {b['p']:.2g})",
                flush=True,
            )
    return out


Banks = dict[tuple[str, str], ScoreBank]
Near = dict[tuple[str, str, str], dict[tuple[float, float], np.ndarray]]
Feats = dict[tuple[str, str, str], tuple[Any, list[Any]]]
Correct = Callable[[HierarchyConfig, str, str], np.ndarray]


def score(
    pool: HierarchyConfig, datasets: str, cache: FeatureCache
) -> tuple[Banks, Near, Feats, dict[str, list[float]]]:
    """Per protocol part: the pool's bank, each descriptor's features and its grid's
    nearest-neighbour matrices; ms per pair per descriptor."""
    banks: Banks = {}
    near: Near = {}
    feats: Feats = {}
    pair_ms: dict[str, list[float]] = {d: [] for d in DESCRIPTORS}
    for proto in PROTOCOLS:
        for part, split in split_parts(proto, datasets):
            banks[proto, part] = ScoreBank.build(pool, split, cache=cache)
            for d, p in DESCRIPTORS.items():
                if d == "kaze_tuned" and "kaze" in DESCRIPTORS:  # the same features and grid
                    feats[proto, part, d] = feats[proto, part, "kaze"]
                    near[proto, part, d] = near[proto, part, "kaze"]
                    continue
                m = create_method("kaze", p)
                prep = prepare({"k": m}, split, cache=cache)
                feats[proto, part, d] = (prep.db["k"], prep.queries["k"])
                near[proto, part, d], ms = grid_matrices(prep.queries["k"], prep.db["k"])
                pair_ms[d].append(ms)
            print(f"scored {proto} {part}", flush=True)
    return banks, near, feats, pair_ms


def matching_choice(
    banks: Banks, near: Near
) -> tuple[dict[str, dict[str, Any]], dict[str, list[float]]]:
    """Each descriptor's matching setting chosen on the grid (kaze alone, mean training
    recall@1), and the grid's figures (printed)."""

    def alone_train(d: str, t: float, r: float) -> float:
        vals = []
        for p in PROTOCOLS:
            bank, sc = banks[p, "train"], near[p, "train", d][t, r]
            vals.append(float(np.mean(bank.gt[np.arange(bank.n_query), sc.argmin(axis=1)])))
        return float(np.mean(vals))

    print("\n### Matching choice (kaze alone, mean training recall@1)\n")
    print("| descriptor | " + " | ".join(f"{t:g} % / {r:g}" for t, r in GRID) + " |")
    print("|---|" + "---|" * len(GRID))
    chosen: dict[str, dict[str, Any]] = {"kaze": {}}
    grid_rows: dict[str, list[float]] = {}
    for d in DESCRIPTORS:
        vals = [alone_train(d, t, r) for t, r in GRID]
        grid_rows[d] = vals
        print(f"| {d} | " + " | ".join(f"{v:.3f}" for v in vals) + " |", flush=True)
        if d != "kaze":
            best = int(np.argmax(vals))  # first of equals: the strictest setting
            chosen[d] = {"match_threshold": GRID[best][0], "max_ratio": GRID[best][1]}
    return chosen, grid_rows


def add_chosen(
    banks: Banks,
    near: Near,
    feats: Feats,
    params: dict[str, dict[str, Any]],
    with_default: bool,
) -> dict[str, dict[str, HierarchyConfig]]:
    """Every chosen method's scores into the banks (dense for kaze, sparse for inliers);
    returns each descriptor's hierarchy families."""
    configs: dict[str, dict[str, HierarchyConfig]] = {}
    for d in DESCRIPTORS:
        configs[d] = families(d, params[d], with_default)
        for (p, part), bank in banks.items():
            db, qs = feats[p, part, d]
            m = create_method("kaze", params[d])
            if d == "kaze":  # the pool's kaze: the same method, scored by Kaze.scores
                mat = bank.scores["kaze"]
            elif not m.config.binary:  # type: ignore[attr-defined]
                mat = np.stack([np.asarray(m.scores(q, db), np.float64) for q in qs])
            else:  # Hamming distances are exact: the grid path is Kaze.scores
                c = m.config
                mat = near[p, part, d][c.match_threshold, c.max_ratio]  # type: ignore[attr-defined]
                for qi in (0, len(qs) // 2):
                    np.testing.assert_allclose(mat[qi], m.scores(qs[qi], db), atol=1e-9)
            bank.methods[f"kaze_{d}"], bank.scores[f"kaze_{d}"] = m, mat
            bank.features[f"kaze_{d}"] = (db, qs)
            if d in INLIER_DESCRIPTORS and with_default:
                mi = create_method("inliers", params[d])
                bank.methods[f"inliers_{d}"] = mi
                bank.scores[f"inliers_{d}"] = sparse_inliers(bank, mi, (db, qs))
                bank.features[f"inliers_{d}"] = (db, qs)
        print(f"hierarchies of {d} scored", flush=True)
    return configs


def preset_rows(presets: dict[str, HierarchyConfig], correct: Correct) -> dict[str, Any]:
    """The presets as they are: recall@1 on every part (printed)."""
    rows: dict[str, Any] = {}
    print("\n### The presets as they are (recall@1, train / test)\n")
    for n, cfg in presets.items():
        cells = [
            f"{correct(cfg, p, part).mean():.3f}" for p in PROTOCOLS for part in ("train", "test")
        ]
        print(f"| {n} | " + " | ".join(cells) + " |")
        rows[f"preset {n}"] = {"cells": cells}
    return rows


def family_rows(
    configs: dict[str, dict[str, HierarchyConfig]],
    params: dict[str, dict[str, Any]],
    presets: dict[str, HierarchyConfig],
    correct: Correct,
    bank: ScoreBank,
    images: int,
) -> dict[str, Any]:
    """Each structure with each descriptor: recall@1 (test parts signed against KAZE's
    descriptor), ms per query on ``bank`` and bytes per reference (printed)."""
    rows: dict[str, Any] = {}
    print("\n### Recall@1 (+-2 frames); test cells: won/lost vs KAZE's descriptor, sign test p\n")
    print("| structure | descriptor | " + " | ".join(f"{p} train | {p} test" for p in PROTOCOLS)
          + " | mean train | mean test | ms/query | bytes/ref |")  # fmt: skip
    print("|---|---|" + "---|---|" * len(PROTOCOLS) + "---|---|---|---|")
    for fam in configs["kaze"]:
        for d in DESCRIPTORS:
            if fam not in configs[d]:
                continue
            cfg, base = configs[d][fam], configs["kaze"][fam]
            cells, trains, tests, signs = [], [], [], {}
            for p in PROTOCOLS:
                tr, te = correct(cfg, p, "train"), correct(cfg, p, "test")
                trains.append(tr.mean())
                tests.append(te.mean())
                cells.append(f"{tr.mean():.3f}")
                if d == "kaze":
                    cells.append(f"{te.mean():.3f}")
                    continue
                t = paired_test(te, correct(base, p, "test"))
                signs[p] = t
                if fam.startswith("default"):  # also against the default preset itself
                    signs[f"{p} vs default"] = paired_test(
                        te, correct(presets["default"], p, "test")
                    )
                cells.append(f"{te.mean():.3f} (+{t['wins']}/-{t['losses']}, p {t['p']:.2g})")
            timing = measure_query_ms(cfg, bank, images=images, threads=1)
            size = bytes_per_reference(bank, cfg)
            rows[f"{fam} | {d}"] = {
                "params": params[d], "train": trains, "test": tests, "sign": signs,
                "mean_train": float(np.mean(trains)), "mean_test": float(np.mean(tests)),
                "timing": timing, "bytes_per_reference": size,
            }  # fmt: skip
            print(
                f"| {fam} | {d} | " + " | ".join(cells)
                + f" | {np.mean(trains):.3f} | {np.mean(tests):.3f} | {timing['total_ms']:.1f} "
                f"| {size:,.0f} |",
                flush=True,
            )  # fmt: skip
    return rows


def select(ap: argparse.ArgumentParser, descriptors: str | None) -> None:
    """Keep only ``descriptors`` (comma-separated; kaze always) in :data:`DESCRIPTORS`."""
    if not descriptors:
        return
    keep = {"kaze", *descriptors.split(",")}
    if keep - set(DESCRIPTORS):
        ap.error(f"unknown descriptors: {', '.join(sorted(keep - set(DESCRIPTORS)))}")
    for d in set(DESCRIPTORS) - keep:
        del DESCRIPTORS[d]


def main() -> int:
    ap = parser(__doc__)
    add_data(ap)
    ap.add_argument("--time-images", type=int, default=10)
    add_json(ap)
    ap.add_argument(
        "--descriptors",
        help=f"comma-separated subset of {', '.join(DESCRIPTORS)} (kaze, the baseline, always)",
    )
    ap.add_argument(
        "--no-default",
        action="store_true",
        help="kaze alone and the handcrafted preset only (no CNN method is scored)",
    )
    ap.add_argument("--time-only", action="store_true", help="only time each descriptor")
    ap.add_argument(
        "--control",
        metavar="THRESHOLD,RATIO",
        help="only KAZE's descriptor with this matching (alone, handcrafted) against its default",
    )
    args = ap.parse_args()
    select(ap, args.descriptors)
    cache = FeatureCache(args.cache_dir)
    print(machine(), flush=True)
    if args.time_only:
        timing = time_descriptors(Path(args.datasets))
        if args.json:
            write_record(args.json, {"time_only": timing}, args)
        return 0
    if args.control:
        t, r = (float(v) for v in args.control.split(","))
        matching = {"match_threshold": t, "max_ratio": r}
        runs = control(Path(args.datasets), cache, matching)
        if args.json:
            results = {"matching": matching, "control": runs}
            write_record(args.json, results, args, config="handcrafted")
        return 0
    pool = pool_config(("handcrafted",) if args.no_default else ("default", "handcrafted"))
    banks, near, feats, pair_ms = score(pool, args.datasets, cache)
    chosen, grid_rows = matching_choice(banks, near)
    params = {d: {**DESCRIPTORS[d], **chosen[d]} for d in DESCRIPTORS}
    print("chosen: " + "; ".join(f"{d} {chosen[d]}" for d in DESCRIPTORS))
    print(
        "ms per pair (nearest two): "
        + ", ".join(f"{d} {np.mean(v):.3f}" for d, v in pair_ms.items() if v)
    )
    configs = add_chosen(banks, near, feats, params, not args.no_default)

    def correct(cfg: HierarchyConfig, p: str, part: str) -> np.ndarray:
        return np.asarray(banks[p, part].run(cfg).correct, bool)

    presets = {
        n: load_config(n) for n in ("handcrafted",) + (() if args.no_default else ("default",))
    }
    rows = preset_rows(presets, correct)
    bank = banks[next(iter(PROTOCOLS)), "test"]
    rows.update(family_rows(configs, params, presets, correct, bank, args.time_images))
    if args.json:
        results = {
            "grid": [list(g) for g in GRID],
            "grid_train": grid_rows,
            "chosen": chosen,
            "pair_ms": {d: float(np.mean(v)) for d, v in pair_ms.items() if v},
            "rows": rows,
        }
        write_record(args.json, results, args, config=pool, default=float)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
