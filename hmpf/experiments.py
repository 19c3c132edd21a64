"""The paper's studies (Hausler & Milford 2020, Section IV) on any route's training split.

:func:`run_studies` reproduces, on a :class:`~hmpf.study.ScoreBank` of the training part:

1. recall@N of every method alone (Fig. 2 and 3);
2. every two-tier hierarchy of a trio of methods, both orders and a method stacked on itself
   (Fig. 4 and 5);
3. every order of the trio in three tiers, with the mean recall@1 per tier position
   (Fig. 6 and 7);
4. six methods, two per tier, in the paper's arrangements Exp1-Exp6 with the compute time per
   query (Fig. 8 and 9, Table I);
5. flat fusion against 50 and 10 candidates, and the scaled counts (Fig. 10);
6. the hierarchy with the best training Combined recall@1 among studies 2-5 (the paper's way
   of choosing) and, when given, a calibrated one, on the test part against their best single
   method and flat fusion.

"Recall@1 of a tier" is the original's ``recall_top1_by_level``: the best reference of the
tier's mean normalised score. :func:`write_figures` draws the figures (PNG) and
:func:`report_markdown` the tables.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.calibrate import compare_on, describe
from hmpf.config import HierarchyConfig
from hmpf.errors import ConfigError
from hmpf.study import CostModel, ScoreBank, derive_config, measure_query_ms

__all__ = ["PAPER_SIX", "check_pool", "report_markdown", "run_studies", "write_figures"]

#: Table I: the pairs and their order per experiment (tier 1 first).
PAPER_PAIRS = {"A": ("netvlad", "hog"), "B": ("hybridnet", "gist"), "C": ("kaze", "olo")}
PAPER_SIX = {
    "Exp1": "ABC",
    "Exp2": "ACB",
    "Exp3": "BAC",
    "Exp4": "BCA",
    "Exp5": "CBA",
    "Exp6": "CAB",
}
NAMES = {
    "gem": "GeM",
    "netvlad": "NetVLAD",
    "hybridnet": "HybridNet",
    "olo": "OLO",
    "gist": "Gist",
    "hog": "HOG",
    "sad": "SAD",
    "kaze": "KAZE",
}


def _name(mid: str) -> str:
    return NAMES.get(mid, mid)


def _row(
    bank: ScoreBank, pool: HierarchyConfig, tiers: Sequence[tuple[Sequence[str], int]]
) -> tuple[HierarchyConfig, dict[str, Any]]:
    cfg = derive_config(pool, tiers, None, name="study")
    out = bank.run(cfg)
    return cfg, {
        "hierarchy": describe([t for t, _ in tiers], [k for _, k in tiers]),
        "tiers": [list(t) for t, _ in tiers],
        "k": [k for _, k in tiers],
        "tier_top1": out.tier_top1,
        "tier_recall": out.tier_recall,
        "combined": out.recall_at_1,
    }


def check_pool(pool: HierarchyConfig, trio: Sequence[str], count_trio: Sequence[str]) -> None:
    """The studies' methods (the trios and Table I's six) must all be in the pool."""
    needed = set(trio) | set(count_trio) | {m for p in PAPER_PAIRS.values() for m in p}
    missing = sorted(needed - set(pool.method_ids))
    if missing:
        raise ConfigError(
            f"the studies need methods missing from the pool: {', '.join(missing)} "
            f"(pool: {', '.join(pool.method_ids)})"
        )


def run_studies(
    pool: HierarchyConfig,
    train: ScoreBank,
    test: ScoreBank | None,
    *,
    costs: CostModel | None = None,
    trio: Sequence[str] = ("gist", "netvlad", "kaze"),
    count_trio: Sequence[str] = ("netvlad", "kaze", "olo"),
    k1: int = 20,
    k2: int = 5,
    counts: Sequence[tuple[int, int]] = ((50, 10), (20, 5)),
    calibrated: HierarchyConfig | None = None,
    time_images: int = 10,
) -> dict[str, Any]:
    """Run the six studies; returns a JSON-ready dict (see the module docstring)."""
    check_pool(pool, trio, count_trio)
    nd = train.n_db
    ns = list(range(1, min(nd, 50) + 1))
    res: dict[str, Any] = {
        "k1": k1,
        "k2": k2,
        "n_reference": nd,
        "n_query": train.n_query,
        "tier_score": pool.tier_score,
    }
    res["single"] = {m: train.single_recall(m, ns) for m in pool.method_ids}
    res["recall_ns"] = ns
    chosen: list[tuple[float, HierarchyConfig, str]] = []

    def keep(cfg: HierarchyConfig, row: dict[str, Any], study: str) -> None:
        chosen.append((row["combined"], cfg, f"{study}: {row['hierarchy']}"))

    res["two_tier"] = []
    for a, b in itertools.product(trio, trio):
        cfg, row = _row(train, pool, [((a,), k1), ((b,), 1)])
        res["two_tier"].append(row)
        keep(cfg, row, "2")
    res["three_tier"] = []
    for order in itertools.permutations(trio):
        cfg, row = _row(train, pool, [((order[0],), k1), ((order[1],), k2), ((order[2],), 1)])
        res["three_tier"].append(row)
        keep(cfg, row, "3")
    rows = res["three_tier"]
    res["three_tier_mean"] = {
        "first": float(np.mean([r["tier_top1"][0] for r in rows])),
        "second": float(np.mean([r["tier_top1"][1] for r in rows])),
        "third": float(np.mean([r["tier_top1"][2] for r in rows])),
        "combined": float(np.mean([r["combined"] for r in rows])),
    }
    res["six"] = []
    for exp, arrangement in PAPER_SIX.items():
        tiers = [
            (PAPER_PAIRS[arrangement[0]], k1),
            (PAPER_PAIRS[arrangement[1]], k2),
            (PAPER_PAIRS[arrangement[2]], 1),
        ]
        cfg, row = _row(train, pool, tiers)
        row["experiment"] = exp
        row["measured_ms"] = measure_query_ms(cfg, train, images=time_images)
        if costs is not None:
            row["model_ms"] = costs.query_ms(cfg, train.run(cfg).mean_inputs)
        res["six"].append(row)
        keep(cfg, row, exp)
    res["counts"] = []
    settings: list[tuple[str, int, int]] = [("flat (all references)", nd, nd)]
    for c1, c2 in counts:
        settings += [(f"{c1} candidates", c1, nd), (f"{c1} then {c2}", c1, c2)]
    for label, c1, c2 in settings:
        cfg, row = _row(
            train, pool, [((count_trio[0],), c1), ((count_trio[1],), c2), ((count_trio[2],), 1)]
        )
        row["setting"] = label
        res["counts"].append(row)
        keep(cfg, row, "5")
    best = max(chosen, key=lambda x: x[0])  # first of equals: the earliest study
    res["chosen"] = {"label": best[2], "train_combined": best[0]}
    if test is not None:
        res["test"] = []
        finalists = [("best of studies 2-5", best[1])]
        if calibrated is not None:
            finalists.append(("calibrated", calibrated))
        for label, cfg in finalists:
            cmp = compare_on(test, pool, cfg)
            cmp.pop("outcome")
            res["test"].append(
                {
                    "label": label,
                    "hierarchy": describe(
                        [t.methods for t in cfg.tiers], [t.k for t in cfg.tiers], cfg.tier_weights
                    ),
                    "train_combined": train.run(cfg).recall_at_1,
                    **cmp,
                    "measured_ms": measure_query_ms(cfg, test, images=time_images),
                }
            )
    return res


# -- figures ------------------------------------------------------------------------------------


def _bars(ax: Any, groups: list[str], series: dict[str, list[float]], ylabel: str) -> None:
    n = len(series)
    width = 0.8 / n
    x = np.arange(len(groups))
    for i, (label, values) in enumerate(series.items()):
        ax.bar(x + (i - (n - 1) / 2) * width, values, width, label=label)
    ax.set_xticks(x)
    ax.set_xticklabels(groups, rotation=30, ha="right", fontsize=9)
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 1.18)  # room for the legend above the bars
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", ncol=n, frameon=False)


def _tier_series(rows: Sequence[dict[str, Any]], labels: Sequence[str]) -> dict[str, list[float]]:
    """Bar series: each tier's recall@1 under its label, then the Combined recall@1."""
    series = {lab: [r["tier_top1"][i] for r in rows] for i, lab in enumerate(labels)}
    series["Combined"] = [r["combined"] for r in rows]
    return series


def _arrow(tiers: Sequence[Sequence[str]]) -> str:
    return " → ".join("+".join(_name(m) for m in t) for t in tiers)


def write_figures(res: dict[str, Any], out: str | Path, title: str = "") -> list[Path]:
    """Draw the studies' figures as PNG files in ``out``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    suffix = f" ({title})" if title else ""
    paths: list[Path] = []

    def save(fig: Any, name: str) -> None:
        fig.tight_layout()
        p = out / name
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ns = res["recall_ns"]
    for mid, rec in res["single"].items():
        ax.plot(ns, [rec[n] for n in ns], label=_name(mid), linewidth=1.8)
    ax.set_xlabel("N (number of top candidates)")
    ax.set_ylabel("Recall @ N")
    ax.set_ylim(0, 1.02)
    ax.set_xlim(1, ns[-1])
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9, loc="lower right")
    ax.set_title(f"Every method alone, training split{suffix}")
    save(fig, "fig1_recall_at_n.png")

    def tier_figure(
        rows: list[dict[str, Any]], groups: list[str], labels: list[str], title: str, name: str
    ) -> None:
        fig, ax = plt.subplots(figsize=(9, 4.5))
        _bars(ax, groups, _tier_series(rows, labels), "Recall @ 1")
        ax.set_title(title + suffix)
        save(fig, name)

    first = ["first method", "second method", "third method"]
    rows = res["two_tier"]
    tier_figure(
        rows,
        [_arrow(r["tiers"]) for r in rows],
        first[:2],
        f"Two methods in two tiers (top {res['k1']} passed on)",
        "fig2_two_tier.png",
    )
    rows = res["three_tier"]
    tier_figure(
        rows,
        [_arrow(r["tiers"]) for r in rows],
        first,
        f"Three methods in three tiers ({res['k1']} then {res['k2']})",
        "fig3_three_tier.png",
    )

    rows = res["six"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.5), gridspec_kw={"width_ratios": [3, 1.3]})
    _bars(
        ax,
        [r["experiment"] for r in rows],
        _tier_series(rows, ["tier 1", "tier 2", "tier 3"]),
        "Recall @ 1",
    )
    ax.set_xticklabels([r["experiment"] for r in rows], rotation=0, ha="center")
    ax.set_title(f"Six methods, two per tier{suffix}")
    ax2.bar([r["experiment"] for r in rows], [r["measured_ms"]["total_ms"] for r in rows])
    ax2.set_ylabel("time per query (ms, measured)")
    ax2.set_title("Compute time")
    ax2.grid(axis="y", alpha=0.3)
    save(fig, "fig4_six_methods.png")

    rows = res["counts"]
    tier_figure(
        rows,
        [r["setting"] for r in rows],
        [f"{_name(t[0])} (tier {i})" for i, t in enumerate(rows[0]["tiers"], start=1)],
        "Candidates passed between tiers",
        "fig5_candidates.png",
    )

    if res.get("test"):
        rows = res["test"]
        fig, ax = plt.subplots(figsize=(8, 4.5))
        _bars(
            ax,
            [f"{r['label']}\n{r['hierarchy']}" for r in rows],
            {
                "hierarchy (Combined)": [r["recall_at_1"] for r in rows],
                "best single method": [r["best_single_recall_at_1"] for r in rows],
                "flat fusion of its methods": [r["flat_recall_at_1"] for r in rows],
            },
            "Recall @ 1 (test split)",
        )
        ax.set_xticklabels([r["label"] for r in rows], rotation=0, ha="center")
        ax.set_title(f"Chosen hierarchies on the test split{suffix}")
        save(fig, "fig6_test.png")
    return paths


# -- report -------------------------------------------------------------------------------------


def _f(x: float) -> str:
    return f"{x:.3f}"


def _tier_row(label: str, r: dict[str, Any]) -> str:
    """``| label | R@1 of each tier | Combined |``."""
    return f"| {label} | " + " | ".join(_f(t) for t in r["tier_top1"]) + f" | {_f(r['combined'])} |"


def report_markdown(res: dict[str, Any], title: str, figures: Sequence[Path] = ()) -> str:
    """The studies' tables in Markdown (figures linked by file name)."""
    fig = {p.name: p.name for p in figures}
    L: list[str] = [f"## {title}", ""]
    L.append(
        f"Training split: {res['n_query']} queries against {res['n_reference']} references; "
        f"candidate counts {res['k1']} (tier 1) and {res['k2']} (tier 2); recall@1 of a tier "
        "is the best reference of that tier's mean score; earlier tiers enter the Combined "
        f"score with the {res.get('tier_score', 'max')} of their methods (`tier_score`)."
    )
    L.append("")

    def img(name: str) -> None:
        if name in fig:
            L.extend([f"![{name}]({name})", ""])

    L.append("### 1. Every method alone (recall@N)")
    L.append("")
    ns = [n for n in (1, 5, 10, 20, 50) if n in res["recall_ns"]]
    L.append("| method | " + " | ".join(f"R@{n}" for n in ns) + " |")
    L.append("|---|" + "---|" * len(ns))
    for mid, rec in res["single"].items():
        L.append(f"| {_name(mid)} | " + " | ".join(_f(rec[n]) for n in ns) + " |")
    L.append("")
    img("fig1_recall_at_n.png")

    L.append("### 2. Two tiers")
    L.append("")
    L.append("| hierarchy | first method R@1 | second method R@1 | Combined |")
    L.append("|---|---|---|---|")
    L.extend(_tier_row(_arrow(r["tiers"]), r) for r in res["two_tier"])
    L.append("")
    img("fig2_two_tier.png")

    L.append("### 3. Three tiers, every order")
    L.append("")
    L.append("| hierarchy | first | second | third | Combined |")
    L.append("|---|---|---|---|---|")
    L.extend(_tier_row(_arrow(r["tiers"]), r) for r in res["three_tier"])
    m = res["three_tier_mean"]
    L.append(
        f"| **mean per position** | {_f(m['first'])} | {_f(m['second'])} | {_f(m['third'])} "
        f"| {_f(m['combined'])} |"
    )
    L.append("")
    img("fig3_three_tier.png")

    L.append("### 4. Six methods, two per tier (Table I)")
    L.append("")
    L.append(
        "| experiment | tier 1 | tier 2 | tier 3 | R@1 tiers 1/2/3 | Combined "
        "| ms/query measured | ms/query modelled |"
    )
    L.append("|---|---|---|---|---|---|---|---|")
    for r in res["six"]:
        t = r["tier_top1"]
        names = ["+".join(_name(x) for x in tier) for tier in r["tiers"]]
        model = f"{r['model_ms']:.1f}" if "model_ms" in r else "n/a"
        L.append(
            f"| {r['experiment']} | {names[0]} | {names[1]} | {names[2]} | "
            f"{_f(t[0])} / {_f(t[1])} / {_f(t[2])} | {_f(r['combined'])} | "
            f"{r['measured_ms']['total_ms']:.1f} | {model} |"
        )
    L.append("")
    img("fig4_six_methods.png")

    L.append("### 5. Candidate counts")
    L.append("")
    L.append(
        "| setting | "
        + " | ".join(f"{_name(t[0])} R@1" for t in res["counts"][0]["tiers"])
        + " | Combined |"
    )
    L.append("|---|---|---|---|---|")
    L.extend(_tier_row(r["setting"], r) for r in res["counts"])
    L.append("")
    img("fig5_candidates.png")

    L.append("### 6. Chosen hierarchies on the test split")
    L.append("")
    L.append(
        f"Best training Combined among studies 2-5: {res['chosen']['label']} "
        f"({_f(res['chosen']['train_combined'])})."
    )
    L.append("")
    if res.get("test"):
        L.append(
            "| choice | hierarchy | train Combined | test Combined | best single (test) "
            "| flat fusion (test) | ms/query |"
        )
        L.append("|---|---|---|---|---|---|---|")
        for r in res["test"]:
            L.append(
                f"| {r['label']} | {r['hierarchy']} | {_f(r['train_combined'])} | "
                f"**{_f(r['recall_at_1'])}** | {_f(r['best_single_recall_at_1'])} "
                f"({_name(r['best_single'])}) | {_f(r['flat_recall_at_1'])} | "
                f"{r['measured_ms']['total_ms']:.1f} |"
            )
        L.append("")
        img("fig6_test.png")
    return "\n".join(L) + "\n"
