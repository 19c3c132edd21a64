"""The paper's studies (Hausler & Milford 2020, Section IV).

:func:`run_studies` reproduces, on a :class:`~hmpf.evaluation.study.ScoreBank` of any route's
training part:

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
from typing import Any, NamedTuple

import numpy as np

from hmpf.config import HierarchyConfig
from hmpf.errors import ConfigError, MissingDependencyError
from hmpf.evaluation.calibrate import compare_on, describe
from hmpf.evaluation.metrics import HierarchyOutcome
from hmpf.evaluation.study import CostModel, ScoreBank, derive_config, measure_query_ms

__all__ = [
    "PAPER_SIX",
    "check_pool",
    "report_markdown",
    "require_matplotlib",
    "run_studies",
    "write_figures",
]

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


class _Run(NamedTuple):
    """One study hierarchy run on the training bank: its config, its table row and its
    outcome (kept: nothing runs the same hierarchy on the same bank twice)."""

    cfg: HierarchyConfig
    row: dict[str, Any]
    outcome: HierarchyOutcome


def _row(
    bank: ScoreBank, pool: HierarchyConfig, tiers: Sequence[tuple[Sequence[str], int]]
) -> _Run:
    cfg = derive_config(pool, tiers, None, name="study")
    out = bank.run(cfg)
    row = {
        "hierarchy": describe([t for t, _ in tiers], [k for _, k in tiers]),
        "tiers": [list(t) for t, _ in tiers],
        "k": [k for _, k in tiers],
        "tier_top1": out.tier_top1,
        "tier_recall": out.tier_recall,
        "combined": out.recall_at_1,
    }
    return _Run(cfg, row, out)


def check_pool(pool: HierarchyConfig, trio: Sequence[str], count_trio: Sequence[str]) -> None:
    """The studies' methods (the trios and Table I's six) must all be in the pool."""
    needed = set(trio) | set(count_trio) | {m for p in PAPER_PAIRS.values() for m in p}
    missing = sorted(needed - set(pool.method_ids))
    if missing:
        raise ConfigError(
            f"the studies need methods missing from the pool: {', '.join(missing)} "
            f"(pool: {', '.join(pool.method_ids)})"
        )


#: (method ids, k) per tier, tier 1 first.
Tiers = Sequence[tuple[Sequence[str], int]]
#: Every study's hierarchies as (training Combined recall@1, config, label), in study order.
Kept = list[tuple[float, HierarchyConfig, str]]


def _rows(
    bank: ScoreBank, pool: HierarchyConfig, hierarchies: Sequence[tuple[str, Tiers]], kept: Kept
) -> list[_Run]:
    """Run each (study label, tiers) on ``bank``; remember each in ``kept``."""
    out = []
    for study, tiers in hierarchies:
        run = _row(bank, pool, tiers)
        kept.append((run.row["combined"], run.cfg, f"{study}: {run.row['hierarchy']}"))
        out.append(run)
    return out


def _position_means(rows: Sequence[dict[str, Any]]) -> dict[str, float]:
    """Study 3: mean recall@1 per tier position, and of the Combined score."""
    means = {
        pos: float(np.mean([r["tier_top1"][i] for r in rows]))
        for i, pos in enumerate(("first", "second", "third"))
    }
    return {**means, "combined": float(np.mean([r["combined"] for r in rows]))}


def _six(
    train: ScoreBank,
    pool: HierarchyConfig,
    k1: int,
    k2: int,
    costs: CostModel | None,
    time_images: int,
    kept: Kept,
) -> list[dict[str, Any]]:
    """Study 4: Table I's arrangements, each with its measured (and modelled) time."""
    hierarchies = [
        (exp, [(PAPER_PAIRS[arr[0]], k1), (PAPER_PAIRS[arr[1]], k2), (PAPER_PAIRS[arr[2]], 1)])
        for exp, arr in PAPER_SIX.items()
    ]
    rows = []
    for (exp, _), (cfg, row, out) in zip(
        hierarchies, _rows(train, pool, hierarchies, kept), strict=True
    ):
        row["experiment"] = exp
        row["measured_ms"] = measure_query_ms(cfg, train, images=time_images)
        if costs is not None:
            row["model_ms"] = costs.query_ms(cfg, out.mean_inputs)
        rows.append(row)
    return rows


def _counts(
    train: ScoreBank,
    pool: HierarchyConfig,
    count_trio: Sequence[str],
    counts: Sequence[tuple[int, int]],
    kept: Kept,
) -> list[dict[str, Any]]:
    """Study 5: flat, then each (c1, c2) as c1 candidates alone and c1 then c2."""
    nd = train.n_db
    settings: list[tuple[str, int, int]] = [("flat (all references)", nd, nd)]
    for c1, c2 in counts:
        settings += [(f"{c1} candidates", c1, nd), (f"{c1} then {c2}", c1, c2)]
    a, b, c = ((m,) for m in count_trio)
    hierarchies = [("5", [(a, c1), (b, c2), (c, 1)]) for _, c1, c2 in settings]
    rows = [run.row for run in _rows(train, pool, hierarchies, kept)]
    for (label, _, _), row in zip(settings, rows, strict=True):
        row["setting"] = label
    return rows


def _on_test(
    test: ScoreBank,
    pool: HierarchyConfig,
    finalists: Sequence[tuple[str, HierarchyConfig, float]],
    time_images: int,
    sequence_train: ScoreBank | None = None,
) -> list[dict[str, Any]]:
    """Study 6: each (label, config, training Combined recall@1) on the test part against
    its baselines; with ``sequence_train``, also in sequence mode (the filter's settings
    chosen on that training part)."""
    rows = []
    for label, cfg, train_combined in finalists:
        cmp = compare_on(test, pool, cfg)
        cmp.pop("outcome")
        if sequence_train is not None:
            params, _ = sequence_train.tune_sequence(cfg)
            cmp["sequence"] = test.sequence(cfg, params)
        rows.append(
            {
                "label": label,
                "hierarchy": describe(
                    [t.methods for t in cfg.tiers], [t.k for t in cfg.tiers], cfg.tier_weights
                ),
                "train_combined": train_combined,
                **cmp,
                "measured_ms": measure_query_ms(cfg, test, images=time_images),
            }
        )
    return rows


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
    sequence: bool = False,
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
    kept: Kept = []
    two: list[tuple[str, Tiers]] = [
        ("2", [((a,), k1), ((b,), 1)]) for a, b in itertools.product(trio, trio)
    ]
    res["two_tier"] = [run.row for run in _rows(train, pool, two, kept)]
    three: list[tuple[str, Tiers]] = [
        ("3", [((a,), k1), ((b,), k2), ((c,), 1)]) for a, b, c in itertools.permutations(trio)
    ]
    res["three_tier"] = [run.row for run in _rows(train, pool, three, kept)]
    res["three_tier_mean"] = _position_means(res["three_tier"])
    res["six"] = _six(train, pool, k1, k2, costs, time_images, kept)
    res["counts"] = _counts(train, pool, count_trio, counts, kept)
    best = max(kept, key=lambda x: x[0])  # first of equals: the earliest study
    res["chosen"] = {"label": best[2], "train_combined": best[0]}
    if test is not None:
        # The best one's training recall is known; the calibrated one runs on train once.
        finalists = [("best of studies 2-5", best[1], best[0])]
        if calibrated is not None:
            finalists.append(("calibrated", calibrated, train.run(calibrated).recall_at_1))
        res["test"] = _on_test(test, pool, finalists, time_images, train if sequence else None)
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


def require_matplotlib() -> None:
    """Raise :class:`MissingDependencyError` with an install hint when figures cannot be drawn.

    Call it before any long work: the figures are drawn last.
    """
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise MissingDependencyError(
            "the experiments draw figures with matplotlib, which is not installed: "
            "pip install 'hmpf[report]'"
        ) from exc


class _Figures:
    """A folder of PNG figures drawn with matplotlib (Agg, no display)."""

    def __init__(self, out: Path, title: str) -> None:
        import matplotlib  # figures only (the report extra)

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # figures only (the report extra)

        self.plt = plt
        self.out = out
        self.suffix = f" ({title})" if title else ""
        self.paths: list[Path] = []

    def save(self, fig: Any, name: str) -> None:
        fig.tight_layout()
        path = self.out / name
        fig.savefig(path, dpi=110)
        self.plt.close(fig)
        self.paths.append(path)

    def single(self, res: dict[str, Any]) -> None:
        """Fig. 1: recall@N of every method alone."""
        fig, ax = self.plt.subplots(figsize=(7, 4.5))
        ns = res["recall_ns"]
        for mid, rec in res["single"].items():
            ax.plot(ns, [rec[n] for n in ns], label=_name(mid), linewidth=1.8)
        ax.set_xlabel("N (number of top candidates)")
        ax.set_ylabel("Recall @ N")
        ax.set_ylim(0, 1.02)
        ax.set_xlim(1, ns[-1])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=9, loc="lower right")
        ax.set_title(f"Every method alone, training split{self.suffix}")
        self.save(fig, "fig1_recall_at_n.png")

    def tiers(
        self,
        rows: list[dict[str, Any]],
        groups: list[str],
        labels: list[str],
        title: str,
        name: str,
    ) -> None:
        """Bars of each tier's recall@1 and the Combined one, per hierarchy."""
        fig, ax = self.plt.subplots(figsize=(9, 4.5))
        _bars(ax, groups, _tier_series(rows, labels), "Recall @ 1")
        ax.set_title(title + self.suffix)
        self.save(fig, name)

    def six(self, rows: list[dict[str, Any]]) -> None:
        """Fig. 4: Table I's arrangements, recall and measured time."""
        fig, (ax, ax2) = self.plt.subplots(
            1, 2, figsize=(11, 4.5), gridspec_kw={"width_ratios": [3, 1.3]}
        )
        _bars(
            ax,
            [r["experiment"] for r in rows],
            _tier_series(rows, ["tier 1", "tier 2", "tier 3"]),
            "Recall @ 1",
        )
        ax.set_xticklabels([r["experiment"] for r in rows], rotation=0, ha="center")
        ax.set_title(f"Six methods, two per tier{self.suffix}")
        ax2.bar([r["experiment"] for r in rows], [r["measured_ms"]["total_ms"] for r in rows])
        ax2.set_ylabel("time per query (ms, measured)")
        ax2.set_title("Compute time")
        ax2.grid(axis="y", alpha=0.3)
        self.save(fig, "fig4_six_methods.png")

    def test(self, rows: list[dict[str, Any]]) -> None:
        """Fig. 6: the chosen hierarchies on the test split against their baselines."""
        fig, ax = self.plt.subplots(figsize=(8, 4.5))
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
        ax.set_title(f"Chosen hierarchies on the test split{self.suffix}")
        self.save(fig, "fig6_test.png")


def write_figures(res: dict[str, Any], out: str | Path, title: str = "") -> list[Path]:
    """Draw the studies' figures as PNG files in ``out``; returns their paths."""
    require_matplotlib()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = _Figures(out, title)
    figs.single(res)
    first = ["first method", "second method", "third method"]
    rows = res["two_tier"]
    figs.tiers(
        rows,
        [_arrow(r["tiers"]) for r in rows],
        first[:2],
        f"Two methods in two tiers (top {res['k1']} passed on)",
        "fig2_two_tier.png",
    )
    rows = res["three_tier"]
    figs.tiers(
        rows,
        [_arrow(r["tiers"]) for r in rows],
        first,
        f"Three methods in three tiers ({res['k1']} then {res['k2']})",
        "fig3_three_tier.png",
    )
    figs.six(res["six"])
    rows = res["counts"]
    figs.tiers(
        rows,
        [r["setting"] for r in rows],
        [f"{_name(t[0])} (tier {i})" for i, t in enumerate(rows[0]["tiers"], start=1)],
        "Candidates passed between tiers",
        "fig5_candidates.png",
    )
    if res.get("test"):
        figs.test(res["test"])
    return figs.paths


# -- report -------------------------------------------------------------------------------------


def _f(x: float) -> str:
    return f"{x:.3f}"


def _tier_row(label: str, r: dict[str, Any]) -> str:
    """``| label | R@1 of each tier | Combined |``."""
    return f"| {label} | " + " | ".join(_f(t) for t in r["tier_top1"]) + f" | {_f(r['combined'])} |"


def _md_single(res: dict[str, Any]) -> list[str]:
    ns = [n for n in (1, 5, 10, 20, 50) if n in res["recall_ns"]]
    lines = ["| method | " + " | ".join(f"R@{n}" for n in ns) + " |", "|---|" + "---|" * len(ns)]
    for mid, rec in res["single"].items():
        lines.append(f"| {_name(mid)} | " + " | ".join(_f(rec[n]) for n in ns) + " |")
    return lines


def _md_two(res: dict[str, Any]) -> list[str]:
    return [
        "| hierarchy | first method R@1 | second method R@1 | Combined |",
        "|---|---|---|---|",
        *(_tier_row(_arrow(r["tiers"]), r) for r in res["two_tier"]),
    ]


def _md_three(res: dict[str, Any]) -> list[str]:
    m = res["three_tier_mean"]
    return [
        "| hierarchy | first | second | third | Combined |",
        "|---|---|---|---|---|",
        *(_tier_row(_arrow(r["tiers"]), r) for r in res["three_tier"]),
        f"| **mean per position** | {_f(m['first'])} | {_f(m['second'])} | {_f(m['third'])} "
        f"| {_f(m['combined'])} |",
    ]


def _md_six(res: dict[str, Any]) -> list[str]:
    lines = [
        "| experiment | tier 1 | tier 2 | tier 3 | R@1 tiers 1/2/3 | Combined "
        "| ms/query measured | ms/query modelled |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in res["six"]:
        t = r["tier_top1"]
        names = ["+".join(_name(x) for x in tier) for tier in r["tiers"]]
        model = f"{r['model_ms']:.1f}" if "model_ms" in r else "n/a"
        lines.append(
            f"| {r['experiment']} | {names[0]} | {names[1]} | {names[2]} | "
            f"{_f(t[0])} / {_f(t[1])} / {_f(t[2])} | {_f(r['combined'])} | "
            f"{r['measured_ms']['total_ms']:.1f} | {model} |"
        )
    return lines


def _md_counts(res: dict[str, Any]) -> list[str]:
    methods = " | ".join(f"{_name(t[0])} R@1" for t in res["counts"][0]["tiers"])
    return [
        f"| setting | {methods} | Combined |",
        "|---|---|---|---|---|",
        *(_tier_row(r["setting"], r) for r in res["counts"]),
    ]


def _md_test(res: dict[str, Any]) -> list[str]:
    lines = [
        f"Best training Combined among studies 2-5: {res['chosen']['label']} "
        f"({_f(res['chosen']['train_combined'])})."
    ]
    if res.get("test"):
        lines += [
            "",
            "| choice | hierarchy | train Combined | test Combined | best single (test) "
            "| flat fusion (test) | sequence mode (test) | ms/query |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in res["test"]:
            seq = _f(r["sequence"]["recall_at_1"]) if r.get("sequence") else "-"
            lines.append(
                f"| {r['label']} | {r['hierarchy']} | {_f(r['train_combined'])} | "
                f"**{_f(r['recall_at_1'])}** | {_f(r['best_single_recall_at_1'])} "
                f"({_name(r['best_single'])}) | {_f(r['flat_recall_at_1'])} | {seq} | "
                f"{r['measured_ms']['total_ms']:.1f} |"
            )
    return lines


#: The report's sections: heading, table writer, figure shown under it (when drawn).
SECTIONS = (
    ("### 1. Every method alone (recall@N)", _md_single, "fig1_recall_at_n.png"),
    ("### 2. Two tiers", _md_two, "fig2_two_tier.png"),
    ("### 3. Three tiers, every order", _md_three, "fig3_three_tier.png"),
    ("### 4. Six methods, two per tier (Table I)", _md_six, "fig4_six_methods.png"),
    ("### 5. Candidate counts", _md_counts, "fig5_candidates.png"),
    ("### 6. Chosen hierarchies on the test split", _md_test, "fig6_test.png"),
)


def report_markdown(res: dict[str, Any], title: str, figures: Sequence[Path] = ()) -> str:
    """The studies' tables in Markdown (figures linked by file name)."""
    drawn = {p.name for p in figures}
    lines = [
        f"## {title}",
        "",
        f"Training split: {res['n_query']} queries against {res['n_reference']} references; "
        f"candidate counts {res['k1']} (tier 1) and {res['k2']} (tier 2); recall@1 of a tier "
        "is the best reference of that tier's mean score; earlier tiers enter the Combined "
        f"score with the {res.get('tier_score', 'max')} of their methods (`tier_score`).",
        "",
    ]
    for heading, table, figure in SECTIONS:
        lines += [heading, "", *table(res), ""]
        if figure in drawn and (figure != "fig6_test.png" or res.get("test")):
            lines += [f"![{figure}]({figure})", ""]
    return "\n".join(lines) + "\n"
