"""Train/test splits, score banks, the cost model, the search and the acceptance threshold."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Hashable, Mapping, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import pytest

from hmpf.config import HierarchyConfig, load_config, parse_config
from hmpf.datasets import frame_ground_truth, list_images
from hmpf.errors import ConfigError, DatasetError
from hmpf.evaluation.calibrate import (
    SearchSpace,
    Trial,
    acceptance_threshold,
    calibrate,
    paired_test,
    precision_recall_at,
    search,
)
from hmpf.evaluation.evaluate import EvalData, evaluate
from hmpf.evaluation.study import CostModel, ScoreBank, derive_config, measure_costs, split_data
from hmpf.features import FeatureCache
from hmpf.imageio import load_image
from hmpf.methods import GlobalMethod, Method
from hmpf.methods.base import GroupOutput, euclidean
from tests.conftest import link_route, synthetic_image

POOL = {
    "name": "cheap-pool",
    "methods": {"kaze": {"max_keypoints": 150}},
    "tiers": [{"methods": ["hog", "gist", "sad", "kaze"], "k": 1}],
}
N_IMAGES = 60  # per traverse: blocks of 10 -> 30 training and 30 test frames


def _paths(n: int) -> list[Path]:
    return [Path(f"/x/{i:03d}.png") for i in range(n)]


# -- splits -----------------------------------------------------------------------------------


def test_blocks_split_alternates_stretches_and_keeps_ground_truth():
    data = EvalData(_paths(100), _paths(100), frame_ground_truth(100, 100, 2), "frames +-2")
    train, test = split_data(data, scheme="blocks", block=20)
    idx = lambda ps: [int(p.stem) for p in ps]  # noqa: E731
    assert idx(train.reference) == [*range(0, 20), *range(40, 60), *range(80, 100)]
    assert idx(test.query) == [*range(20, 40), *range(60, 80)]
    assert not set(idx(train.reference)) & set(idx(test.reference))
    full = frame_ground_truth(100, 100, 2)
    tr_r, tr_q = np.array(idx(train.reference)), np.array(idx(train.query))
    assert np.array_equal(train.gt, full[np.ix_(tr_q, tr_r)])
    # Query 20 (first of a test stretch) keeps only its test-part neighbours 20..22.
    assert test.gt[0].sum() == 3


def test_halves_split_and_errors():
    data = EvalData(_paths(10), _paths(8), frame_ground_truth(8, 10, 1), "frames +-1")
    train, test = split_data(data, 0.5, scheme="halves")
    assert (len(train.reference), len(train.query), len(test.reference), len(test.query)) == (
        5,
        4,
        5,
        4,
    )
    assert np.array_equal(test.gt, frame_ground_truth(8, 10, 1)[4:, 5:])
    with pytest.raises(DatasetError, match="unknown split"):
        split_data(data, scheme="random")
    with pytest.raises(DatasetError, match="between 0 and 1"):
        split_data(data, 1.0, scheme="halves")
    with pytest.raises(DatasetError, match="train_fraction must be 0.5"):
        split_data(data, 0.3, scheme="blocks")
    with pytest.raises(DatasetError, match="too few"):
        split_data(data, scheme="blocks", block=20)


# -- acceptance threshold ---------------------------------------------------------------------


def test_acceptance_threshold_hand_computed():
    q = np.array([5.0, 4.0, 3.0, 2.0, 1.0])
    c = np.array([True, True, False, True, False])
    a = acceptance_threshold(q, c, 0.99)
    assert a["threshold"] == 4.0 and a["reached"]
    assert a["precision"] == 1.0 and a["recall"] == pytest.approx(0.4)
    b = acceptance_threshold(q, c, 0.75)  # {5,4,3,2}: 3 of 4 correct
    assert b["threshold"] == 2.0 and b["precision"] == 0.75 and b["n_accepted"] == 4


def test_acceptance_threshold_ties_and_unreachable():
    # A tie at the top between a right and a wrong answer: both or neither are accepted.
    q = np.array([3.0, 3.0, 1.0])
    c = np.array([True, False, True])
    a = acceptance_threshold(q, c, 0.99)
    assert not a["reached"] and a["n_accepted"] == 0 and a["threshold"] > 3.0
    # NaN quality (no answer) is never accepted.
    q2 = np.array([2.0, np.nan])
    c2 = np.array([True, False])
    b = acceptance_threshold(q2, c2, 0.99)
    assert b["threshold"] == 2.0 and b["n_accepted"] == 1
    assert precision_recall_at(q2, c2, 10.0)["precision"] is None


# -- cost model --------------------------------------------------------------------------------


def test_paired_sign_test_hand_computed():
    a = np.array([1, 1, 1, 0, 0, 1], bool)
    b = np.array([0, 0, 1, 1, 0, 1], bool)
    # 2 wins, 1 loss: P(<= 1 of 3 fair coin flips) = (1 + 3)/8, two-sided -> 1.0
    assert paired_test(a, b) == {"wins": 2, "losses": 1, "p": 1.0}
    five = paired_test(np.ones(7, bool), np.array([0, 0, 0, 0, 0, 1, 1], bool))
    assert (five["wins"], five["losses"]) == (5, 0)
    assert five["p"] == pytest.approx(2 / 32)  # 2 * (1/2)^5
    assert paired_test(a, a)["p"] == 1.0
    with pytest.raises(ValueError, match="same queries"):
        paired_test(a, b[:5])


def test_paired_sign_test_on_a_long_route():
    """Over 1,024 discordant queries: 2.0**n overflowed a float; the exact p still comes."""
    wins, losses = 620, 520  # 1140 discordant queries, plus 100 both got right
    a = np.array([True] * wins + [False] * losses + [True] * 100)
    b = np.array([False] * wins + [True] * losses + [True] * 100)
    n = wins + losses
    exact = 2 * Fraction(sum(math.comb(n, i) for i in range(losses + 1)), 2**n)
    t = paired_test(a, b)
    assert (t["wins"], t["losses"]) == (wins, losses)
    assert t["p"] == pytest.approx(float(exact), rel=1e-9)
    assert 0.001 < t["p"] < 0.01  # 54 % of the discordant queries: significant, not wildly
    assert paired_test(b, a)["p"] == pytest.approx(t["p"], rel=1e-12)  # two-sided


def test_cost_model_charges_shared_passes_once_and_reuses_tier1_scores():
    cm = CostModel(
        units={"forward:0": 20.0, "head:a": 1.0, "head:b": 2.0, "extract:c": 5.0},
        method_units={
            "a": ["forward:0", "head:a"],
            "b": ["forward:0", "head:b"],
            "c": ["extract:c"],
        },
        match={"a": (0.5, 0.01), "b": (0.0, 0.02), "c": (0.0, 1.0)},
        fusion_ms=0.1,
        n_db=100,
    )
    assert cm.extract_ms(["a", "b"]) == 23.0  # one forward pass
    cfg = HierarchyConfig.model_validate(
        {"tiers": [{"methods": ["a"], "k": 10}, {"methods": ["a", "c"], "k": 1}]}
    )
    # tier 1: a on 100 refs; tier 2: a is remembered, c on 10 candidates; 2 x fusion
    expected = (20 + 1 + 5) + (0.5 + 0.01 * 100) + (1.0 * 10) + 0.2
    assert cm.query_ms(cfg) == pytest.approx(expected)
    assert cm.query_ms(cfg, [100, 7.5]) == pytest.approx(expected - 2.5)


class _GroupedToy(GlobalMethod):
    """A non-CNN grouped method whose extract_group reports fixed times: shared 10 ms per
    image, own 1 ms (``a``) or 2 ms (any other id)."""

    name = "grouped_cost_test"
    dim = 1
    calls: ClassVar[list[tuple[tuple[str, ...], int]]] = []

    def group_key(self) -> Hashable:
        return ("grouped_cost_test",)

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return np.array([float(image.mean())], np.float32)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    shared_ms = 10.0

    @staticmethod
    def own_ms(mid: str) -> float:
        return 1.0 if mid == "a" else 2.0

    @classmethod
    def extract_group(
        cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]
    ) -> GroupOutput:
        cls.calls.append((tuple(methods), len(images)))
        feats = {mid: [m.extract(im) for im in images] for mid, m in methods.items()}
        own = {mid: [cls.own_ms(mid)] * len(images) for mid in methods}
        return GroupOutput(feats, own, [cls.shared_ms] * len(images))


class _AloneToy(_GroupedToy):
    """Extracted alone (no group key) but declaring shared 3 ms and own 4 ms per image."""

    name = "alone_cost_test"
    shared_ms = 3.0

    @staticmethod
    def own_ms(mid: str) -> float:
        return 4.0

    def group_key(self) -> None:
        return None


def test_measure_costs_uses_declared_groups_of_any_method(tmp_path: Path):
    """A non-CNN grouped method is costed by its own extract_group: one shared unit per group
    plus each member's own unit, one image at a time after a warm-up."""
    folder = tmp_path / "img"
    folder.mkdir()
    for i in range(6):
        cv2.imwrite(str(folder / f"{i:03d}.png"), synthetic_image(i)[:, :, ::-1])
    paths = list_images(folder)
    data = EvalData(paths[:3], paths[3:], frame_ground_truth(3, 3, 0), "frames +-0")
    methods: dict[str, Method] = {"a": _GroupedToy(), "c": _AloneToy(), "b": _GroupedToy()}
    feats: dict[str, Any] = {}
    scores: dict[str, np.ndarray] = {}
    for mid, m in methods.items():
        db = m.stack([m.extract(load_image(p)) for p in data.reference])
        qs = [m.extract(load_image(p)) for p in data.query]
        feats[mid] = (db, qs)
        scores[mid] = np.stack([m.scores(q, db) for q in qs])
    bank = ScoreBank(methods, scores, np.asarray(data.gt, bool), data, feats)
    _GroupedToy.calls.clear()
    costs = measure_costs(bank, images=3)
    # warm-up + 3 images, each alone; a and b in one call per image
    assert _GroupedToy.calls == [(("a", "b"), 1)] * 4 + [(("c",), 1)] * 4
    assert costs.units == {"forward:0": 10.0, "head:a": 1.0, "head:b": 2.0, "extract:c": 7.0}
    assert costs.method_units == {
        "a": ["forward:0", "head:a"],
        "b": ["forward:0", "head:b"],
        "c": ["extract:c"],
    }
    assert costs.extract_ms(["a", "b"]) == 13.0 and costs.extract_ms(["a", "c"]) == 18.0
    assert CostModel.from_dict(json.loads(json.dumps(costs.to_dict()))) == costs


# -- on real images ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def banks(gardens_point: Path, gp_feature_cache: Path):
    cache = FeatureCache(gp_feature_cache)
    refs = list_images(gardens_point / "day_right")[:N_IMAGES]
    qrys = list_images(gardens_point / "night_right")[:N_IMAGES]
    data = EvalData(refs, qrys, frame_ground_truth(N_IMAGES, N_IMAGES, 2), "frames +-2")
    train_data, test_data = split_data(data, scheme="blocks", block=10)
    pool = parse_config(POOL)
    train = ScoreBank.build(pool, train_data, cache=cache, workers=2)
    test = ScoreBank.build(pool, test_data, cache=cache, workers=2)
    return pool, train, test, train_data, cache


def test_bank_runs_equal_the_real_evaluation(banks):
    """The bank's gathered scores give exactly the answers of the per-query evaluation."""
    pool, train, _, train_data, cache = banks
    for tiers in (
        [(("gist", "hog"), 5), (("kaze",), 1)],
        [(("sad",), 8), (("hog",), 3), (("gist", "kaze"), 1)],
    ):
        for tier_score in ("max", "mean"):
            src = pool.model_copy(update={"tier_score": tier_score})
            cfg = derive_config(src, tiers, None)
            assert cfg.tier_score == tier_score  # inherited from the pool
            rep = evaluate(cfg, train_data, cache=cache, skip_curves=list(cfg.method_ids))
            out = train.run(cfg)
            assert out.matches.tolist() == rep["hierarchy"]["matches"]
            assert out.recall_at_1 == rep["hierarchy"]["combined_recall_at_1"]
            assert out.tier_top1 == [t["top1_recall"] for t in rep["hierarchy"]["tiers"]]
    # One method alone: per-query correctness agrees with its recall@1.
    for mid in pool.method_ids:
        assert train.single_correct(mid).mean() == train.single_recall(mid, [1])[1]


def test_search_is_deterministic_respects_budget_and_ranks(banks):
    pool, train, _, _, _ = banks
    costs = measure_costs(train, images=2)
    assert all(v > 0 for k, v in costs.units.items() if k.startswith("extract:"))
    space = SearchSpace(tuple(pool.method_ids), k1=(3, 6), k2=(2,), samples=40, refine=3)
    calls: list[tuple[int, int]] = []
    a = search(train, pool, costs, space, seed=1, progress=lambda d, t: calls.append((d, t)))
    b = search(train, pool, costs, space, seed=1)
    # Progress counts every structure of the first pass and every refined setting: it rises
    # by one per call, its total grows once (refinement), and it ends at its total.
    done = [d for d, _ in calls]
    assert done == list(range(1, len(calls) + 1)) and calls[-1][0] == calls[-1][1]
    assert len({t for _, t in calls}) == 2 and len(a) <= len(calls)
    assert [c.label() for c in a] == [c.label() for c in b]
    assert [c.sort_key() for c in a] == sorted(c.sort_key() for c in a)
    three = lambda r: {c.tiers for c in r if len(c.tiers) == 3}  # noqa: E731
    assert three(search(train, pool, costs, space, seed=2)) != three(a)
    # The winner's recall is what a fresh run of its config gives.
    assert train.run(a[0].config(pool)).recall_at_1 == a[0].recall_at_1
    # A budget below the cheapest hierarchy's model leaves some out, never one over it.
    budget = float(np.median([c.model_ms for c in a]))
    limited = search(train, pool, costs, space, seed=1, budget_ms=budget)
    assert limited and len(limited) < len(a)
    assert all(c.model_ms <= budget for c in limited)


def test_calibrate_stores_threshold_and_checks_test(banks):
    pool, train, test, _, _ = banks
    space = SearchSpace(tuple(pool.method_ids), k1=(3, 6), k2=(2,), samples=20, refine=2)
    config, rep = calibrate(pool, train, test, space, budget_ms=None, seed=0, target_precision=0.9)
    assert config.acceptance is not None and config.acceptance.precision == 0.9
    acc = rep["train"]["acceptance"]
    assert config.acceptance.threshold == pytest.approx(acc["threshold"], abs=1e-6)
    if acc["reached"]:
        assert acc["precision"] >= 0.9
    te = rep["test"]
    assert te["best_single"] in config.method_ids
    # The sign tests count the queries the differences in recall are made of.
    n = te["n_query"]
    for key, other in (
        ("vs_flat", "flat_recall_at_1"),
        ("vs_best_single", "best_single_recall_at_1"),
    ):
        t = te[key]
        assert t["wins"] - t["losses"] == round((te["recall_at_1"] - te[other]) * n)
        assert 0.0 < t["p"] <= 1.0
    assert te["measured_ms"]["total_ms"] > 0 and te["measured_ms"]["images"] >= 1
    # The config round-trips through YAML and keeps only the methods it uses.
    assert set(config.methods) <= set(config.method_ids)
    with pytest.raises(ConfigError, match="budget"):
        calibrate(pool, train, None, space, budget_ms=0.001, seed=0)


def test_calibrate_with_sequence_tunes_the_filter_on_train_and_reports_test(banks):
    pool, train, test, _, _ = banks
    space = SearchSpace(tuple(pool.method_ids), k1=(3,), k2=(2,), samples=5, refine=1)
    config, rep = calibrate(pool, train, test, space, budget_ms=None, seed=0, sequence=True)
    assert config.sequence is not None and "lock_mass" in config.sequence
    params = config.sequence_params()  # the written settings load back
    assert params.lock_mass == pytest.approx(max(rep["train"]["sequence"]["lock_mass"], 1e-6))
    assert len(rep["train"]["sequence"]["grid"]) > 1
    seq = rep["test"]["sequence"]
    assert seq["n_query"] == test.n_query
    assert seq["params"]["lock_mass"] == pytest.approx(params.lock_mass)
    assert 0 <= seq["recall_at_1"] <= 1 and seq["single_recall_at_1"] == rep["test"]["recall_at_1"]
    # The config digest ignores the filter's settings: an index built for the plain winner
    # serves the sequence one.
    assert config.digest() == config.model_copy(update={"sequence": None}).digest()


def test_trial_config_carries_pool_parameters(banks):
    pool = banks[0]
    c = Trial((("kaze",), ("gist",)), (5, 1), (0.5, 1.0), 0.5, 1.0)
    cfg = c.config(pool)
    assert cfg.methods == {"kaze": {"max_keypoints": 150}}
    assert cfg.weights == [0.5, 1.0] and cfg.tiers[0].k == 5
    with pytest.raises(ConfigError, match="not in the pool"):
        derive_config(pool, [(("olo",), 1)])


def test_calibrate_cli_writes_loadable_config(
    gardens_point: Path, gp_feature_cache: Path, tmp_path: Path, banks
):
    pool_file = tmp_path / "pool.yaml"
    pool_file.write_text(json.dumps(POOL))
    sub = link_route(gardens_point, tmp_path, N_IMAGES)
    out = tmp_path / "cal"
    cmd = [
        sys.executable, "-m", "hmpf.cli.calibrate", "--quiet",
        "--reference", str(sub["day_right"]), "--query", str(sub["night_right"]),
        "--block", "10", "--pool", str(pool_file), "--out", str(out),
        "--cache-dir", str(gp_feature_cache), "--k1", "3", "6", "--k2", "2",
        "--samples", "20", "--refine", "2", "--seed", "3",
    ]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    cfg = load_config(out / "calibrated.yaml")
    rep = json.loads((out / "calibration.json").read_text())
    assert cfg.acceptance is not None
    assert cfg.acceptance.threshold == pytest.approx(rep["train"]["acceptance"]["threshold"])
    assert rep["train"]["winner"]["hierarchy"] == cfg.description
    assert "| 1 |" in (out / "leaderboard.md").read_text()
    assert set(rep["costs"]["match_ms"]) == {"hog", "gist", "sad", "kaze"}
    # --methods: only those are searched, and only those are scored (the banks hold the
    # restricted pool, so KAZE's costly full score matrix is never computed).
    sub_out = tmp_path / "cal-hog-gist"
    only = [*cmd[:-2], "--seed", "3", "--methods", "hog", "gist", "hog"]  # named twice: once
    only[only.index(str(out))] = str(sub_out)
    proc = subprocess.run(only, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    rep2 = json.loads((sub_out / "calibration.json").read_text())
    assert set(rep2["costs"]["match_ms"]) == {"hog", "gist"}
    assert set(load_config(sub_out / "calibrated.yaml").method_ids) <= {"hog", "gist"}
    # Bad input: a clear message, exit 2, no traceback.
    bad = subprocess.run(
        [*cmd[:-2], "--seed", "3", "--methods", "nope"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "not in the pool" in bad.stderr and "Traceback" not in bad.stderr


def test_extended_pool_lets_a_route_pick_the_new_levers(
    gardens_point: Path, gp_feature_cache: Path, tmp_path: Path
):
    """``--pool calibration-pool-extended``: whitened HOG / Gist (fitted on the references),
    multi-scale GeM and BEBLID inlier verification are searchable, and a config using them
    carries their parameters and loads."""
    sub = link_route(gardens_point, tmp_path, N_IMAGES)
    out = tmp_path / "cal"
    levers = {"hog_w": "hog", "gist_w": "gist", "gem_ms": "gem", "inliers_b": "inliers"}
    cmd = [
        sys.executable, "-m", "hmpf.cli.calibrate", "--quiet",
        "--reference", str(sub["day_right"]), "--query", str(sub["night_right"]),
        "--block", "10", "--pool", "calibration-pool-extended", "--out", str(out),
        "--cache-dir", str(gp_feature_cache), "--k1", "3", "6", "--k2", "2",
        "--samples", "20", "--refine", "2", "--seed", "3",
        "--methods", "hog", *levers,
        # a budget no candidate reaches: on a loaded machine the measured costs grow, and a
        # 150 ms budget then dropped some levers' candidates from the search
        "--budget-ms", "1000000",
    ]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((out / "calibration.json").read_text())
    assert set(rep["costs"]["match_ms"]) == {"hog", *levers}
    board = (out / "leaderboard.md").read_text()
    assert all(mid in board for mid in levers)  # searched
    cfg = load_config(out / "calibrated.yaml")
    assert set(cfg.method_ids) <= {"hog", *levers}
    pool = load_config("calibration-pool-extended")
    for mid in set(cfg.method_ids) - {"hog"}:
        assert cfg.method_spec(mid) == pool.method_spec(mid)
        assert cfg.method_spec(mid)[0] == levers[mid]
    assert pool.method_spec("gem_ms")[1]["scales"] == [1.0, 0.5]
    assert pool.method_spec("inliers_b")[1]["descriptor"] == "beblid"
    assert set(load_config("calibration-pool").method_ids) < set(pool.method_ids)


def test_fixed_cost_model_round_trips_and_is_used(banks):
    """A cost model read back from a report gives the same search on any machine."""
    pool, train, _, _, _ = banks
    costs = CostModel(
        units={f"extract:{m}": ms for m, ms in (("hog", 4.1), ("gist", 4.4), ("sad", 1.0))}
        | {"extract:kaze": 48.2},
        method_units={m: [f"extract:{m}"] for m in ("hog", "gist", "sad", "kaze")},
        match={"hog": (0.1, 0.002), "gist": (0.1, 0.001), "sad": (0.0, 0.01), "kaze": (0.3, 0.9)},
        fusion_ms=0.05,
        n_db=train.n_db,
    )
    back = CostModel.from_dict(json.loads(json.dumps({"costs": costs.to_dict()}))["costs"])
    assert back == costs
    with pytest.raises(ConfigError, match="not a cost model"):
        CostModel.from_dict({"units_ms": {}})
    space = SearchSpace(tuple(pool.method_ids), k1=(3, 6), k2=(2,), samples=10, refine=2)
    _, rep = calibrate(pool, train, None, space, budget_ms=60.0, seed=0, costs=back)
    assert rep["costs"] == costs.to_dict()
    assert rep["train"]["winner"]["model_ms"] == costs.query_ms(
        rep_config(pool, rep), train.run(rep_config(pool, rep)).mean_inputs
    )
    # KAZE alone costs 48.2 ms to extract plus 0.9 ms per reference: over a 60 ms budget.
    assert all("kaze" not in c["hierarchy"] for c in rep["train"]["leaderboard"])


def rep_config(pool: HierarchyConfig, rep: dict) -> HierarchyConfig:
    w = rep["train"]["winner"]
    return derive_config(pool, list(zip(w["tiers"], w["k"], strict=True)), w["weights"])


def test_calibrate_cli_version_and_ctrl_c(monkeypatch, capsys, tmp_path: Path):
    from hmpf.cli import calibrate as cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("hmpf-calibrate (hmpf ")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "load_banks", interrupted)
    argv = ["--reference", str(tmp_path), "--query", str(tmp_path), "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 130
    err = capsys.readouterr().err
    assert err == "hmpf-calibrate: interrupted\n"


def _weak_calibration(pool, train, test):
    """Calibrate one weak method alone (its training answers are right and wrong, so a model
    can be fit), with sequence mode: (config, report, the search space, the method)."""
    weak = min(pool.method_ids, key=lambda m: (train.single_recall(m, [1])[1], m))
    space = SearchSpace((weak,), max_tiers=1, max_per_tier=1, samples=1, refine=1)
    config, rep = calibrate(
        pool, train, test, space, budget_ms=None, seed=0, target_precision=0.9, sequence=True
    )
    return config, rep, space, weak


def test_calibrate_fits_confidence_models_that_load_and_round_trip(banks, tmp_path: Path):
    """With sequence mode: both models and thresholds are written into ``acceptance``, the
    z threshold stays, the config round-trips through YAML and the report has the test
    part's figures for the model and the z / mass rules."""
    from hmpf.cli.calibrate import write_config
    from hmpf.confidence import ConfidenceModel
    from hmpf.evaluation.acceptance import SEQUENCE_MODEL_FEATURES, SINGLE_FEATURES
    from hmpf.evaluation.calibrate import leaderboard_markdown

    pool, train, test, _, _ = banks
    config, rep, space, _ = _weak_calibration(pool, train, test)
    acc = config.acceptance
    assert acc is not None and math.isfinite(acc.threshold)
    tr = rep["train"]["confidence"]
    for mode, names, key, thr in (
        ("single", SINGLE_FEATURES, "model", acc.model_threshold),
        ("sequence", SEQUENCE_MODEL_FEATURES, "sequence_model", acc.sequence_threshold),
    ):
        if "skipped" in tr[mode]:  # one class only on this small part: no model, said why
            assert getattr(acc, key) is None
            continue
        model = ConfidenceModel.from_dict(getattr(acc, key), expected=names)
        assert model.features == names and thr is not None and 0 <= thr <= 1
        assert tr[mode]["threshold"] == thr
        te = rep["test"]["confidence"][mode]
        assert te["model"]["rule"] == "p_correct" and 0 <= te["model"]["accepted"] <= 1
        assert te["model"]["ece"] is not None and 0 <= te["model"]["ece"] <= 1
        base = te["z" if mode == "single" else "mass"]
        assert base["n"] == te["model"]["n"] and "ece" not in base
    assert tr["single"].get("skipped") is None  # the weak hierarchy errs on training
    write_config(config, tmp_path / "c.yaml", "test")
    again = load_config(tmp_path / "c.yaml")
    assert again == config and again.acceptance is not None
    assert again.acceptance.confidence_model() == acc.confidence_model()
    assert "Confidence models" in leaderboard_markdown(rep)
    # --no-model: the z threshold only.
    plain, rep2 = calibrate(pool, train, None, space, budget_ms=None, seed=0, model=False)
    assert plain.acceptance is not None and plain.acceptance.model is None
    assert "confidence" not in rep2["train"]


def test_eval_report_applies_the_configs_model_or_says_which_rule_decided(banks):
    """hmpf-eval's report: p_correct per answer from the config's model (null without one),
    the accepted share / precision / ECE at the config's threshold and the rule that
    decided, single frame and sequence mode."""
    from hmpf.evaluation.acceptance import SINGLE_FEATURES
    from hmpf.evaluation.evaluate import format_report

    pool, train, _, train_data, cache = banks
    config, _, _, weak = _weak_calibration(pool, train, None)
    acc = config.acceptance
    assert acc is not None and acc.model is not None
    rep = evaluate(config, train_data, cache=cache, skip_curves=[weak], sequence=True)
    single = rep["acceptance"]["single"]
    assert single["rule"] == "p_correct" and single["threshold"] == acc.model_threshold
    p = np.array(single["p_correct"])
    assert p.shape == (train.n_query,) and ((p > 0) & (p < 1)).all()
    assert single["accepted_answers"] == (p >= acc.model_threshold).tolist()
    assert single["accepted"] == pytest.approx(np.mean(p >= acc.model_threshold))
    # The model's predictions are those of the stored model on the answers' features.
    from hmpf.confidence import answer_features
    from hmpf.sequence import RouteMap

    routes = RouteMap.from_metadata(train.n_db)
    res = train.results(config)
    f0 = answer_features(res[0], routes, profile=train.profile(config))
    assert p[0] == pytest.approx(acc.confidence_model().predict(f0))
    assert set(acc.confidence_model().features) == set(SINGLE_FEATURES)
    seq = rep["acceptance"]["sequence"]
    expected = "p_correct" if acc.sequence_model is not None else "lock"
    assert seq["rule"] == expected and len(seq["p_correct"]) == train.n_query
    text = format_report(rep)
    assert "acceptance (single, rule p_correct: p_correct >=" in text
    # Without a model: the quality (z) rule decides, p_correct is null (never made up).
    plain = config.model_copy(
        update={
            "acceptance": acc.model_copy(
                update={
                    "model": None,
                    "model_threshold": None,
                    "sequence_model": None,
                    "sequence_threshold": None,
                }
            )
        }
    )
    rep2 = evaluate(plain, train_data, cache=cache, skip_curves=[weak], sequence=True)
    s2, q2 = rep2["acceptance"]["single"], rep2["acceptance"]["sequence"]
    assert s2["rule"] == "quality" and s2["p_correct"] == [None] * train.n_query
    assert s2["threshold"] == acc.threshold and "ece" not in s2
    quality = np.nan_to_num(np.array(rep2["hierarchy"]["quality"], dtype=float), nan=-np.inf)
    assert s2["accepted_answers"] == (quality >= acc.threshold).tolist()
    assert q2["rule"] == "lock" and q2["threshold"] == plain.sequence_params().lock_mass
    assert "rule quality: Combined z >=" in format_report(rep2)
    # No acceptance settings at all: the quality rule at the built-in threshold, as the
    # service (one policy: hmpf.acceptance).
    from hmpf.acceptance import DEFAULT_ACCEPT_THRESHOLD

    bare = evaluate(
        config.model_copy(update={"acceptance": None}), train_data, cache=cache, skip_curves=[weak]
    )
    b = bare["acceptance"]["single"]
    assert b["rule"] == "quality" and b["threshold"] == DEFAULT_ACCEPT_THRESHOLD
    assert b["accepted_answers"] == (quality >= DEFAULT_ACCEPT_THRESHOLD).tolist()
    assert "sequence" not in bare["acceptance"]


def test_outside_answers_and_the_threshold_that_keeps_them_out(banks):
    """The training part's own out-of-map answers: each stretch of queries answered against
    the map without the stretch's references (every answer wrong by construction); the
    fitted threshold accepts at most 1 - target of them out of fold."""
    from hmpf.evaluation.acceptance import (
        FOLDS,
        SEQUENCE_MODEL_FEATURES,
        SINGLE_FEATURES,
        fit_acceptance,
        outside_answers,
        single_answers,
    )
    from hmpf.sequence import FilterParams, RouteMap

    pool, train, _, _, _ = banks
    config = derive_config(pool, [(("gist", "hog"), 5), (("kaze",), 1)], None)
    profile = train.profile(config)
    assert profile.methods == ("gist", "hog") and profile.n == train.n_db
    single, seq = outside_answers(train, config, profile, FilterParams())
    assert len(single) > 0 and not single.correct.any()
    nq = train.n_query
    fold = np.minimum(np.arange(nq) * FOLDS // nq, FOLDS - 1)
    for q in single.query:
        removed = train.gt[fold == fold[q]].any(axis=0)
        assert not (train.gt[q] & ~removed).any(), "a right reference was left in the map"
    assert {f for a in single.features for f in a} >= set(SINGLE_FEATURES)
    assert seq is not None and len(seq) > 0 and not seq.correct.any()
    assert set(seq.query) <= set(single.query)
    assert {f for a in seq.features for f in a} >= set(SEQUENCE_MODEL_FEATURES)
    # The first stretch answered by hand: the same answer and features.
    first = single.query[fold[single.query] == 0]
    keep = np.flatnonzero(~train.gt[fold == 0].any(axis=0))
    sub = train.subset(keep)
    res = sub.results(config)
    want = single_answers(
        [res[int(q)] for q in first], None, RouteMap.from_metadata(len(keep)), profile.subset(keep)
    )
    assert want.features == single.features[: len(first)]
    # The threshold keeps the out-of-map answers out (out of fold).
    inside = single_answers(
        train.results(config), train.gt, RouteMap.from_metadata(train.n_db), profile
    )
    target = 0.9
    _, thr, figs = fit_acceptance(inside, SINGLE_FEATURES, target, single)
    assert figs["outside"]["n"] == len(single)
    assert figs["outside"]["accepted_out_of_fold"] <= 1 - target + 1e-12
    assert thr >= figs["outside"]["floor"]
    _, thr0, figs0 = fit_acceptance(inside, SINGLE_FEATURES, target)
    assert "outside" not in figs0


def test_a_routes_own_fit_carries_the_given_models_off_map_terms(banks):
    """carried_terms reads the staged hinges of a single-frame model (the shipped default's
    among them) and nothing else; fit_acceptance with ``carried`` fits the other features
    exactly as without, adds the terms as they were, and chooses the threshold on the
    out-of-fold predictions of that model (so an answer the terms lower can fall below it)."""
    from hmpf.confidence import ConfidenceModel, ModelError, feature_matrix, threshold_for_precision
    from hmpf.config import AcceptanceSettings
    from hmpf.evaluation.acceptance import (
        OUTSIDE_SHARE,
        SINGLE_FEATURES,
        _fit,
        _folds,
        carried_terms,
        fit_acceptance,
        outside_answers,
        outside_floor,
        single_answers,
    )
    from hmpf.sequence import RouteMap

    shipped = load_config("default").acceptance
    assert shipped is not None and shipped.model is not None
    sm = ConfidenceModel.from_dict(shipped.model)
    want = {n: c for n, c in zip(sm.features, sm.coef, strict=True) if n.endswith("_low")}
    assert carried_terms(shipped) == want and set(want) == {"ref_z_low", "cand_z_low"}
    assert carried_terms(None) == {} and carried_terms(AcceptanceSettings(threshold=3.0)) == {}

    pool, train, _, _, _ = banks
    config = derive_config(pool, [(("gist", "hog"), 5), (("kaze",), 1)], None)
    profile = train.profile(config)
    inside = single_answers(
        train.results(config), train.gt, RouteMap.from_metadata(train.n_db), profile
    )
    single, _ = outside_answers(train, config, profile)
    target = 0.9
    plain, _, _ = fit_acceptance(inside, SINGLE_FEATURES, target, single)
    kept, thr, figs = fit_acceptance(inside, SINGLE_FEATURES, target, single, carried=want)
    assert kept.features == (*SINGLE_FEATURES, "ref_z_low", "cand_z_low")
    assert kept == plain.with_terms(want)
    # the out-of-fold predictions recomputed fold by fold, the terms added to each fold
    names = kept.features
    n_in, n_out = len(inside), len(single)
    X = feature_matrix([*inside.features, *single.features], names)
    y = np.concatenate([inside.correct, np.zeros(n_out)]).astype(float)
    share = OUTSIDE_SHARE / (1 - OUTSIDE_SHARE) * n_in / n_out
    w = np.concatenate([np.ones(n_in), np.full(n_out, share)])
    # where a hinge is below 0 the terms lower p, elsewhere nothing moves
    low = (X[:, -2:] < 0).any(axis=1)
    assert low.any(), "no answer where a hinge is below 0: the check is empty"
    p_kept, p_plain = kept.predict(X), plain.predict(X[:, :-2])
    assert np.all(p_kept[low] < p_plain[low])
    np.testing.assert_allclose(p_kept[~low], p_plain[~low], rtol=1e-12, atol=0)
    assert figs["threshold"] == thr and 0 < thr <= 1
    groups = _folds(np.concatenate([inside.query, single.query]))
    oof = np.empty(len(y))
    for g in np.unique(groups):
        hold = groups == g
        fold = _fit(X[~hold, :-2], y[~hold], SINGLE_FEATURES, w[~hold]).with_terms(want)
        oof[hold] = fold.predict(X[hold])
    floor = outside_floor(oof[n_in:], 1 - target)
    assert figs["outside"]["floor"] == floor
    assert thr == threshold_for_precision(oof[:n_in], inside.correct, target, floor=floor)
    # names that are fitted and carried at once, or carried into a gated model: refused
    with pytest.raises(ModelError, match="fitted features"):
        fit_acceptance(inside, SINGLE_FEATURES, target, single, carried={"ref_z": 1.0})
    with pytest.raises(ModelError, match="gated"):
        fit_acceptance(inside, SINGLE_FEATURES, target, single, carried=want, gate=True)
    # a gated model (its main part holding a raw hinge), or a hinge fitted with the others
    # (not raw), carries nothing
    gate = ConfidenceModel(("ref_z",), (0.0,), (1.0,), (1.0,), 0.0)
    gated = ConfidenceModel(
        ("ref_z", "ref_z_low"), (1.0, 0.0), (1.0, 1.0), (0.5, 0.4), 0.1, gate=gate
    )
    raw = ConfidenceModel(("ref_z", "ref_z_low"), (1.0, 0.0), (1.0, 1.0), (0.5, 0.4), 0.1)
    joint = ConfidenceModel(("ref_z", "ref_z_low"), (1.0, -0.3), (1.0, 0.5), (0.5, 0.4), 0.1)
    for m, carried in ((gated, {}), (joint, {}), (raw, {"ref_z_low": 0.4})):
        acc = AcceptanceSettings(threshold=3.0, model=m.to_dict(), model_threshold=0.9)
        assert carried_terms(acc) == carried
