"""Fitting on the references: PCA-whitening and database-side augmentation (DBA).

    python -m bench.reference_fitting [--json out.json] [--time-images 5]

Routes: the three Gardens Point protocols (``hmpf.datasets.GARDENS_POINT_PROTOCOLS``,
``blocks`` split of 20 frames) and Nordland summer -> winter 64x32 (``blocks`` split of 100
frames, as ``calibrated/nordland_handcrafted`` was calibrated), ground truth +-2 frames.

1. Each part's base methods are extracted once (descriptor cache) into a
   :class:`~hmpf.evaluation.study.ScoreBank`: Gardens Point the ``default`` config's
   (GeM, NetVLAD, OLO, Gist) plus HOG; Nordland SAD, HOG, Gist.
2. Variants are derived from those features with the real methods: a variant is created
   from its config (``whiten`` / ``whiten_power`` / ``whiten_shrink`` / ``dba``), its
   whitening fitted (:meth:`GlobalMethod.fit_references`) on the part's references that
   :func:`hmpf.features.fit_methods` would pick (<= 500, evenly spaced), each descriptor
   finished by :meth:`GlobalMethod.finish` (what extraction does after the method's own
   descriptor) and the references stacked by :meth:`Method.stack_references` (DBA).
   ``tests/hmpf/methods/test_reference_fitting.py`` checks this route equals fit + extraction.
3. Settings are chosen on the TRAINING parts only: per method, the whitening setting of the
   grid and the DBA ``k`` with the best mean training recall@1 over the routes the method
   is used on. Test parts get recall@1 and a paired sign test against the plain method /
   the baseline hierarchy (:func:`hmpf.evaluation.calibrate.paired_test`).
4. Hierarchies: Gardens Point ``default``, Nordland ``calibrated/nordland_handcrafted``, each
   with its methods swapped for the chosen whitened / DBA / both variants, and on Nordland a
   2-tier search (:func:`hmpf.evaluation.calibrate.search`, 2 methods per tier) over plain
   and whitened SAD, HOG and Gist on the training part.

ms per query: end to end on one thread (:func:`hmpf.evaluation.study.measure_query_ms`) on
the first Gardens Point test part and the Nordland test part; bytes per reference: what an
index stores (``exact`` precision).
"""

from __future__ import annotations

import itertools
import json
import time
from typing import Any

import numpy as np

from bench import inliers
from bench.harness import (
    add_data,
    add_json,
    machine,
    parser,
    protocol_data,
    write_record,
)
from hmpf.config import HierarchyConfig, TierConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS
from hmpf.evaluation.calibrate import SearchSpace, paired_test, search
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import (
    ScoreBank,
    measure_costs,
    measure_query_ms,
    split_data,
)
from hmpf.features import FeatureCache
from hmpf.index.storage import storage_dtype
from hmpf.methods import GlobalMethod, create_method

GP_BASE = {"gem": {}, "netvlad": {"clusters": 32}, "olo": {"regions": 100}, "gist": {}, "hog": {}}
NL_BASE = {"sad": {}, "hog": {}, "gist": {}}
#: Whitening grid: output size ("max": as many as the fitting references allow), power, shrink.
WHITEN_GRID = [
    {"whiten": d, "whiten_power": p, "whiten_shrink": s}
    for d, p, s in itertools.product((64, 128, 4096), (0.25, 0.5), (0.1, 1.0))
]
DBA_GRID = [{"dba": k} for k in (1, 2, 3)]
WHITENABLE = ("gem", "gist", "hog", "sad")
MAX_FIT = 500  # hmpf.features.fit_methods' max_images


def fit_pick(n: int) -> np.ndarray:
    """The references :func:`hmpf.features.fit_methods` fits on (same rule)."""
    return np.unique(np.linspace(0, n - 1, min(n, MAX_FIT)).round().astype(np.int64))


def derive(bank: ScoreBank, vid: str, base: str, base_params: dict[str, Any], extra: dict) -> None:
    """Add variant ``vid`` (method ``base`` with ``base_params`` + ``extra``) to ``bank``,
    computed from ``base``'s features in the bank (see the module docstring)."""
    if vid in bank.methods:
        return
    m = create_method(base, {**base_params, **extra})
    assert isinstance(m, GlobalMethod)
    db, qs = bank.features[base]
    raw = [np.asarray(r) for r in db]
    state = bank.methods[base].state_arrays()
    if state:  # the base method's own fitted parameters (NetVLAD's centroids)
        m.load_state(state)
    if m.requires_fit():
        m.fit_references(np.stack([raw[i] for i in fit_pick(len(raw))]))
    own = [m.finish(r) for r in raw]
    own_stack = m.stack(own)
    OWN_BYTES[id(bank), vid] = (
        own_stack.size * storage_dtype(m, own_stack, "exact").itemsize / len(own)
    )
    refs = m.stack_references(own)
    queries = [m.finish(np.asarray(q)) for q in qs]
    bank.methods[vid] = m
    bank.scores[vid] = np.stack([np.asarray(m.scores(q, refs), np.float64) for q in queries])
    bank.features[vid] = (refs, queries)


def alone(mid: str) -> HierarchyConfig:
    return HierarchyConfig(
        name="alone", methods={mid: VARIANT_PARAMS[mid]}, tiers=[TierConfig(methods=[mid], k=1)]
    )


def swapped(base: HierarchyConfig, swap: dict[str, str], name: str) -> HierarchyConfig:
    """``base`` with method ids renamed by ``swap`` (variants' parameters come from banks)."""
    tiers = [TierConfig(methods=[swap.get(m, m) for m in t.methods], k=t.k) for t in base.tiers]
    used = {m for t in tiers for m in t.methods}
    return HierarchyConfig(
        name=name,
        mode=base.mode,
        tier_score=base.tier_score,
        methods={m: p for m, p in VARIANT_PARAMS.items() if m in used},
        tiers=tiers,
        weights=base.weights,
    )


#: (bank id, variant id) -> bytes per reference an index stores: each reference's own
#: descriptor (DBA is applied when the index loads, so it adds nothing).
OWN_BYTES: dict[tuple[int, str], float] = {}

#: Variant id -> its full method parameters (with "type"), filled as variants are made.
VARIANT_PARAMS: dict[str, dict[str, Any]] = {}


def variant_id(base: str, extra: dict[str, Any]) -> str:
    parts = []
    if "whiten" in extra:
        parts.append(f"w{extra['whiten']}p{extra['whiten_power']:g}s{extra['whiten_shrink']:g}")
    if extra.get("dba"):
        parts.append(f"dba{extra['dba']}")
    return f"{base}_{'_'.join(parts)}" if parts else base


def bytes_per_reference(bank: ScoreBank, config: HierarchyConfig) -> float:
    """Mean bytes an index (``exact`` precision) stores per reference for ``config``."""
    own = {mid: v for (b, mid), v in OWN_BYTES.items() if b == id(bank)}
    return inliers.bytes_per_reference(bank, config, own)


METHODS = ("gem", "netvlad", "gist", "hog", "sad")
Chosen = dict[str, dict[str, dict[str, Any] | None]]


class Study:
    """The routes (Gardens Point's protocols and Nordland, each with its base methods and
    split block), their parts' banks, and the variants derived in them."""

    def __init__(self, datasets: str, cache: FeatureCache, t_start: float) -> None:
        self.routes: dict[str, tuple[EvalData, dict[str, dict[str, Any]], int]] = {}
        for proto in GARDENS_POINT_PROTOCOLS:
            self.routes[proto] = (protocol_data(proto, datasets), GP_BASE, 20)
        self.routes["nordland"] = (protocol_data("nordland_s_w", datasets), NL_BASE, 100)
        self.banks: dict[tuple[str, str], ScoreBank] = {}
        for route, (data, base, block) in self.routes.items():
            pool = HierarchyConfig(
                name="pool",
                methods={m: dict(p) for m, p in base.items()},
                tiers=[TierConfig(methods=list(base), k=1)],
            )
            for part, split in zip(("train", "test"), split_data(data, block=block), strict=True):
                self.banks[route, part] = ScoreBank.build(pool, split, cache=cache)
                print(f"scored {route} {part} ({time.perf_counter() - t_start:.0f} s)", flush=True)
        for m, p in {**GP_BASE, **NL_BASE}.items():
            VARIANT_PARAMS[m] = {"type": m, **p}

    def used_on(self, m: str) -> list[str]:
        return [r for r, (_, base, _) in self.routes.items() if m in base]

    def correct(self, config: HierarchyConfig, route: str, part: str) -> np.ndarray:
        return np.asarray(self.banks[route, part].run(config).correct, bool)

    def mean_train(self, config: HierarchyConfig, routes: list[str]) -> float:
        return float(np.mean([self.correct(config, r, "train").mean() for r in routes]))

    def make(self, m: str, extra: dict[str, Any], part: str | None = None) -> str:
        """Variant ``m`` + ``extra`` derived in the banks of ``part`` (both when None)."""
        vid = variant_id(m, extra)
        base = {**GP_BASE, **NL_BASE}[m]
        VARIANT_PARAMS[vid] = {"type": m, **base, **extra}
        for r in self.used_on(m):
            for p in (part,) if part else ("train", "test"):
                derive(self.banks[r, p], vid, m, base, extra)
        return vid


def choose_levers(study: Study, report: dict[str, Any]) -> Chosen:
    """Each method alone: its whitening and DBA settings chosen on the training parts."""
    chosen: Chosen = {}
    print("\n### Each method alone: training mean recall@1 per setting\n", flush=True)
    for m in METHODS:
        rs = study.used_on(m)
        grids = {"whiten": WHITEN_GRID if m in WHITENABLE else [], "dba": DBA_GRID}
        plain_train = study.mean_train(alone(m), rs)
        chosen[m] = {}
        train_rows: dict[str, float] = {"plain": plain_train}
        for lever, grid in grids.items():
            best, best_v = None, plain_train
            for extra in grid:
                vid = study.make(m, extra, "train")
                v = study.mean_train(alone(vid), rs)
                train_rows[vid] = v
                if v > best_v + 1e-12:
                    best, best_v = extra, v
            chosen[m][lever] = best
        # Combined: both levers where both were chosen (else the one chosen, already listed).
        both = {**(chosen[m]["whiten"] or {}), **(chosen[m]["dba"] or {})} or None
        if chosen[m]["whiten"] and chosen[m]["dba"]:
            vid = study.make(m, both, "train")
            train_rows[vid] = study.mean_train(alone(vid), rs)
        chosen[m]["both"] = both
        top = sorted(train_rows.items(), key=lambda kv: -kv[1])[:6]
        print(f"{m} on {', '.join(rs)}: " + "; ".join(f"{k} {v:.3f}" for k, v in top), flush=True)
        report["methods"][m] = {"routes": rs, "train": train_rows, "chosen": chosen[m]}
    return chosen


def test_levers(study: Study, chosen: Chosen, report: dict[str, Any]) -> None:
    """Each method alone with each chosen lever on the test parts, against it plain."""
    print("\n### Each method alone, test parts (recall@1; vs plain: won/lost, sign test p)\n")
    routes_all = list(study.routes)
    print("| method | lever | setting | " + " | ".join(routes_all) + " |")
    print("|---|---|---|" + "---|" * len(routes_all))
    for m in METHODS:
        rows: dict[str, Any] = {}
        for lever in ("plain", "whiten", "dba", "both"):
            extra = {} if lever == "plain" else chosen[m][lever]
            if extra is None:
                continue
            vid = study.make(m, extra, "test") if extra else m
            cells = []
            for r in routes_all:
                if r not in study.used_on(m):
                    cells.append("")
                    continue
                c, c0 = study.correct(alone(vid), r, "test"), study.correct(alone(m), r, "test")
                t = paired_test(c, c0)
                mark = "" if lever == "plain" else f" (+{t['wins']}/-{t['losses']}, p {t['p']:.2g})"
                cells.append(f"{c.mean():.3f}{mark}")
                rows.setdefault(lever, {})[r] = {"recall": float(c.mean()), "sign": t}
            setting = json.dumps(extra) if extra else ""
            print(f"| {m} | {lever} | {setting} | " + " | ".join(cells) + " |", flush=True)
        report["methods"][m]["test"] = rows


def lever_configs(
    study: Study, chosen: Chosen, presets: dict[str, HierarchyConfig]
) -> dict[str, dict[str, HierarchyConfig]]:
    """Per route family, its preset plain and with each chosen lever swapped in."""
    configs: dict[str, dict[str, HierarchyConfig]] = {}
    for key, cfg in presets.items():
        configs[key] = {f"{cfg.name}": swapped(cfg, {}, cfg.name)}
        for lever in ("whiten", "dba", "both"):
            sw = {}
            for m in cfg.method_ids:
                extra = chosen.get(m, {}).get(lever)
                if extra:
                    sw[m] = study.make(m, extra)
            if sw:
                configs[key][f"{cfg.name} + {lever}"] = swapped(cfg, sw, f"{cfg.name}+{lever}")
    return configs


def nordland_search(
    study: Study, chosen: Chosen, thumbs: HierarchyConfig
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """Nordland: a 2-tier search over plain and whitened SAD / HOG / Gist on the training
    part; the winner and the search's report."""
    w_ids = {m: study.make(m, chosen[m]["whiten"]) for m in NL_BASE if chosen[m]["whiten"]}
    pool_ids = [*NL_BASE, *w_ids.values()]
    pool = HierarchyConfig(
        name="pool",
        tier_score=thumbs.tier_score,
        methods={m: VARIANT_PARAMS[m] for m in pool_ids},
        tiers=[TierConfig(methods=pool_ids, k=1)],
    )
    train_bank = study.banks["nordland", "train"]
    sub = ScoreBank(
        {m: train_bank.methods[m] for m in pool_ids},
        {m: train_bank.scores[m] for m in pool_ids},
        train_bank.gt,
        train_bank.data,
        {m: train_bank.features[m] for m in pool_ids},
    )
    t0 = time.perf_counter()
    costs = measure_costs(sub)
    space = SearchSpace(tuple(pool_ids), max_tiers=2, max_per_tier=2, refine=10)
    ranked = search(sub, pool, costs, space, budget_ms=150.0, seed=0)
    win = ranked[0]
    searched = win.config(pool, name="thumbnails")
    print(
        f"\nNordland search: {len(ranked)} hierarchies in {time.perf_counter() - t0:.0f} s; "
        f"chosen on training: {win.label()} (train recall@1 {win.recall_at_1:.3f})",
        flush=True,
    )
    return searched, {
        "pool": pool_ids,
        "space": {"max_tiers": 2, "max_per_tier": 2, "refine": 10},
        "winner": win.label(),
        "train": win.recall_at_1,
        "config": searched.model_dump(mode="json"),
        "leaderboard": [(t.label(), t.recall_at_1) for t in ranked[:10]],
    }


def hierarchy_rows(
    study: Study, configs: dict[str, dict[str, HierarchyConfig]], report: dict[str, Any]
) -> None:
    """Each hierarchy's recall@1 on the parts of its routes, tests against the first row."""
    print("\n### Hierarchies (recall@1, +-2 frames; test vs the first row: won/lost, p)\n")
    for key, rs in (("gp", list(GARDENS_POINT_PROTOCOLS)), ("nordland", ["nordland"])):
        print("| config | " + " | ".join(f"{r} train | {r} test" for r in rs) + " |")
        print("|---|" + "---|---|" * len(rs))
        first = next(iter(configs[key].values()))
        for label, cfg in configs[key].items():
            cells, entry = [], {}
            for r in rs:
                tr, te = study.correct(cfg, r, "train"), study.correct(cfg, r, "test")
                t = paired_test(te, study.correct(first, r, "test"))
                mark = "" if cfg is first else f" (+{t['wins']}/-{t['losses']}, p {t['p']:.2g})"
                cells += [f"{tr.mean():.3f}", f"{te.mean():.3f}{mark}"]
                entry[r] = {"train": float(tr.mean()), "test": float(te.mean()), "sign": t}
            report["hierarchies"][label] = {"config": cfg.model_dump(mode="json"), **entry}
            print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
        print()


def cost_rows(
    study: Study,
    configs: dict[str, dict[str, HierarchyConfig]],
    report: dict[str, Any],
    images: int,
) -> None:
    """ms per query (end to end, one thread) and bytes per reference of each hierarchy."""
    print("### Cost (ms per query end to end, one thread; bytes per reference)\n")
    print("| config | ms per query | extraction ms | hierarchy ms | bytes per reference |")
    print("|---|---|---|---|---|")
    timing_bank = {"gp": study.banks[next(iter(GARDENS_POINT_PROTOCOLS)), "test"]}
    timing_bank["nordland"] = study.banks["nordland", "test"]
    for key in ("gp", "nordland"):
        bank = timing_bank[key]
        for label, cfg in configs[key].items():
            t = measure_query_ms(cfg, bank, images=images, threads=1)
            size = bytes_per_reference(bank, cfg)
            report["hierarchies"][label].update(timing=t, bytes_per_reference=size)
            print(
                f"| {label} | {t['total_ms']:.1f} | {t['extract_ms']:.1f} | "
                f"{t['hierarchy_ms']:.1f} | {size:,.0f} |",
                flush=True,
            )


def main() -> int:
    ap = parser(__doc__)
    add_data(ap)
    ap.add_argument("--time-images", type=int, default=5)
    add_json(ap)
    args = ap.parse_args()
    t_start = time.perf_counter()
    print(machine(), flush=True)
    study = Study(args.datasets, FeatureCache(args.cache_dir), t_start)
    # -- 1. each method alone: the settings chosen on the training parts ---------------------
    report: dict[str, Any] = {"machine": machine(), "methods": {}, "hierarchies": {}}
    chosen = choose_levers(study, report)
    test_levers(study, chosen, report)
    # -- 2. in the hierarchies ---------------------------------------------------------------
    thumbs = load_config("calibrated/nordland_handcrafted")
    configs = lever_configs(study, chosen, {"gp": load_config("default"), "nordland": thumbs})
    searched, report["nordland_search"] = nordland_search(study, chosen, thumbs)
    configs["nordland"][f"searched: {report['nordland_search']['winner']}"] = searched
    hierarchy_rows(study, configs, report)
    cost_rows(study, configs, report, args.time_images)
    report["elapsed_s"] = time.perf_counter() - t_start
    report["variants"] = VARIANT_PARAMS
    if args.json:
        write_record(args.json, report, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
