"""``hmpf-eval experiments`` end to end on a short stretch of Gardens Point (real CNNs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.config import build_methods, load_config
from hmpf.datasets import frame_ground_truth
from hmpf.evaluation import experiments as studies
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import CostModel, ScoreBank, derive_config
from tests.conftest import link_route

N_IMAGES = 40  # per traverse; blocks of 10 -> 20 training and 20 test frames


@pytest.fixture(scope="module")
def short_route(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return link_route(gardens_point, tmp_path_factory.mktemp("route"), N_IMAGES)


def _experiments(
    route: dict[str, Path],
    tmp_path: Path,
    *extra: str,
    launch: tuple[str, ...] = (),
    cache: Path | None = None,
) -> subprocess.CompletedProcess[str]:
    """``hmpf-eval experiments`` on ``route`` (``launch``: another ``python`` entry point;
    ``cache``: the feature cache, by default ``tmp_path / "cache"``)."""
    return subprocess.run(
        [
            sys.executable,
            *(launch or ("-m", "hmpf.cli.eval")),
            "experiments",
            "--quiet",
            "--reference",
            str(route["day_right"]),
            "--query",
            str(route["night_right"]),
            "--block",
            "10",
            "--cache-dir",
            str(cache or tmp_path / "cache"),
            *extra,
        ],  # fmt: skip
        capture_output=True,
        text=True,
        timeout=900,
    )


def test_experiments_write_figures_report_and_tables(
    short_route, gp_feature_cache: Path, tmp_path: Path
):
    out = tmp_path / "exp"
    proc = _experiments(
        short_route,
        tmp_path,
        *("--k1", "6", "--k2", "3", "--out", str(out), "--title", "short GP", "--sequence"),
        cache=gp_feature_cache,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((out / "experiments.json").read_text())
    assert set(res["single"]) == {
        "gem",
        "netvlad",
        "hybridnet",
        "olo",
        "gist",
        "hog",
        "sad",
        "kaze",
    }
    assert len(res["recall_ns"]) == 20 and res["recall_ns"][0] == 1
    for rec in res["single"].values():
        vals = [rec[str(n)] for n in res["recall_ns"]]
        assert vals == sorted(vals) and 0 <= vals[0] <= 1  # recall@N never falls with N
        assert vals[-1] == 1.0  # N = every reference
    # Study 2: 3 x 3 two-tier hierarchies, a method stacked on itself included.
    pairs = [tuple(t[0] for t in r["tiers"]) for r in res["two_tier"]]
    assert len(pairs) == 9 and ("gist", "gist") in pairs and ("kaze", "netvlad") in pairs
    # Study 3: the 6 orders of the trio, with the per-position means.
    assert len({tuple(t[0] for t in r["tiers"]) for r in res["three_tier"]}) == 6
    mean_first = sum(r["tier_top1"][0] for r in res["three_tier"]) / 6
    assert res["three_tier_mean"]["first"] == pytest.approx(mean_first)
    # Study 4: Table I's six arrangements of six methods, each timed.
    assert [r["experiment"] for r in res["six"]] == [f"Exp{i}" for i in range(1, 7)]
    assert res["six"][5]["tiers"] == [["kaze", "olo"], ["netvlad", "hog"], ["hybridnet", "gist"]]
    assert all(r["measured_ms"]["total_ms"] > 0 for r in res["six"])
    # Study 5: flat (every reference passes) is the first setting.
    assert res["counts"][0]["k"][:2] == [20, 20]
    # Study 6: the best training hierarchy on the test part, with its baselines.
    t = res["test"][0]
    assert t["best_single"] in {m for tier in res["six"][0]["tiers"] for m in tier} | set(
        res["single"]
    )
    assert 0 <= t["recall_at_1"] <= 1 and 0 <= t["flat_recall_at_1"] <= 1
    # --sequence: the same hierarchy driven in order on the test part.
    assert t["sequence"]["n_query"] == 20 and 0 <= t["sequence"]["recall_at_1"] <= 1
    for i in range(1, 7):
        png = next(out.glob(f"fig{i}_*.png"))
        head = png.read_bytes()[:8]
        assert head == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    report = (out / "report.md").read_text()
    for section in ("### 1.", "### 2.", "### 3.", "### 4.", "### 5.", "### 6.", "Exp6", "sequence"):
        assert section in report
    assert "![fig4_six_methods.png](fig4_six_methods.png)" in report


def test_experiments_reject_unknown_trio(short_route, tmp_path: Path):
    proc = _experiments(
        short_route, tmp_path, "--trio", "gist", "netvlad", "surf", "--out", str(tmp_path / "x")
    )
    assert proc.returncode == 2 and "surf" in proc.stderr and "Traceback" not in proc.stderr


def test_experiments_without_matplotlib_stop_before_any_work(short_route, tmp_path: Path):
    """Without the ``report`` extra: one line with the install hint, before any extraction."""
    # As for a user who lacks matplotlib: every import of it fails in this interpreter.
    code = (
        "import sys; sys.modules['matplotlib'] = None; "
        "from hmpf.cli.eval import main; sys.exit(main(sys.argv[1:]))"
    )
    cache, out = tmp_path / "cache", tmp_path / "exp"
    proc = _experiments(short_route, tmp_path, "--out", str(out), launch=("-c", code))
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "pip install 'hmpf[report]'" in proc.stderr and "Traceback" not in proc.stderr
    assert not cache.exists() and not out.exists()  # nothing extracted, nothing written


def test_experiments_ctrl_c_is_one_line(monkeypatch, capsys, tmp_path: Path):
    from hmpf.cli import eval as cli
    from hmpf.cli import experiments

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(experiments, "load_banks", interrupted)
    argv = ["experiments", "--reference", str(tmp_path), "--query", str(tmp_path)]
    assert cli.main([*argv, "--out", str(tmp_path / "exp")]) == 130
    assert capsys.readouterr().err == "hmpf-eval experiments: interrupted\n"


def test_each_hierarchy_runs_once_on_each_bank(monkeypatch):
    """The studies reuse each run's outcome (model time, training recall of the chosen one)
    instead of running a hierarchy on the same bank again; gathered random scores suffice."""
    pool = load_config("calibration-pool")
    methods = build_methods(pool)
    rng = np.random.default_rng(0)

    def bank(n: int) -> ScoreBank:
        paths = [Path(f"/x/{i:03d}.png") for i in range(n)]
        data = EvalData(paths, paths, frame_ground_truth(n, n, 1), "frames +-1")
        scores = {m: rng.random((n, n)) for m in methods}
        return ScoreBank(methods, scores, np.asarray(data.gt, bool), data)

    train, test = bank(20), bank(20)
    runs: list[tuple[str, str]] = []
    original = ScoreBank.run

    def counting(self: ScoreBank, config):  # type: ignore[no-untyped-def]
        runs.append(("train" if self is train else "test", config.model_dump_json()))
        return original(self, config)

    monkeypatch.setattr(ScoreBank, "run", counting)
    monkeypatch.setattr(studies, "measure_query_ms", lambda *a, **k: {"total_ms": 1.0})
    costs = CostModel(
        units={f"extract:{m}": 1.0 for m in methods},
        method_units={m: [f"extract:{m}"] for m in methods},
        match={m: (0.0, 0.01) for m in methods},
        fusion_ms=0.1,
        n_db=20,
    )
    calibrated = derive_config(pool, [(("hog", "gist"), 5), (("kaze",), 1)], None)
    res = studies.run_studies(
        pool, train, test, costs=costs, k1=6, k2=3, counts=((6, 3),), calibrated=calibrated
    )
    assert len(runs) == len(set(runs))  # no hierarchy twice on one bank
    n_rows = sum(len(res[s]) for s in ("two_tier", "three_tier", "six", "counts"))
    # Every study row once on train, the calibrated one once more; on test each finalist
    # and the flat fusion of its methods.
    assert sum(b == "train" for b, _ in runs) == n_rows + 1
    assert sum(b == "test" for b, _ in runs) == 4
    assert all(r["model_ms"] > 0 for r in res["six"])
    best, cal = res["test"]
    assert best["train_combined"] == res["chosen"]["train_combined"]
    assert cal["train_combined"] == original(train, calibrated).recall_at_1
