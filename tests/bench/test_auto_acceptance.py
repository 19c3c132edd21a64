"""bench/auto_acceptance.py's pure helpers on synthetic answers: combining two policies, the
accepted(-and-right) flags through the one policy, the sign tests and the pooled counts."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.acceptance import Policy
from hmpf.confidence import ConfidenceModel
from hmpf.evaluation.acceptance import Answers
from hmpf.sequence import Estimate

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def aa():
    path = ROOT / "bench" / "auto_acceptance.py"
    spec = importlib.util.spec_from_file_location("bench_auto_acceptance", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _model(feature: str) -> ConfidenceModel:
    """p = sigmoid(4 * x) of one feature."""
    return ConfidenceModel((feature,), (0.0,), (1.0,), (4.0,), 0.0)


def _answers(x: np.ndarray, correct: np.ndarray, mass: np.ndarray) -> Answers:
    n = len(x)
    feats = [{"quality": float(v), "tier1_margin": float(v), "sequence_logit": float(v)} for v in x]
    ests = [Estimate(i, float(m), False, i + 1, continuous=i > 0) for i, m in enumerate(mass)]
    return Answers(feats, correct, np.asarray(x), np.arange(n), ests, np.zeros(n, np.int64))


def test_combine_takes_single_frame_rules_from_one_and_sequence_rules_from_the_other(aa):
    single = Policy(threshold=2.5, model=_model("quality"), model_threshold=0.9)
    seq = Policy(
        model=_model("tier1_margin"),
        model_threshold=0.5,
        sequence_model=_model("sequence_logit"),
        sequence_threshold=0.95,
        sequence_stay_threshold=0.5,
        lock_mass=0.98,
        unlock_mass=0.8,
    )
    both = aa.combine(single, seq)
    assert both.model is single.model and both.model_threshold == 0.9 and both.threshold == 2.5
    assert both.sequence_model is seq.sequence_model
    assert (both.sequence_threshold, both.sequence_stay_threshold) == (0.95, 0.5)
    assert (both.lock_mass, both.unlock_mass) == (0.98, 0.8)
    assert both.single_rule == "p_correct" and both.sequence_rule == "p_correct"
    # without a sequence model on the sequence side, the lock rule stays
    assert aa.combine(seq, single).sequence_rule == "lock"


def test_route_flags_go_through_the_policy_and_sign_tests_count_discordant_answers(aa):
    x = np.array([2.0, 1.0, 0.1, -1.0, 2.0, 0.8])
    correct = np.array([True, True, True, False, False, True])
    mass = np.array([0.995, 0.995, 0.5, 0.995, 0.995, 0.2])
    answers = {
        "single": _answers(x, correct, mass),
        "sequence": _answers(x, correct, mass),
        "foreign_single": _answers(x, np.zeros(6, bool), mass),
        "foreign_sequence": _answers(x, np.zeros(6, bool), mass),
    }
    strict = Policy(model=_model("quality"), model_threshold=0.99)  # p >= 0.99: x >= 1.15
    loose = Policy(model=_model("quality"), model_threshold=0.9)  # x >= 0.55
    got = aa.route_flags({"pseudo": strict, "shipped": loose}, answers)
    assert got["single"]["pseudo"].tolist() == [True, False, False, False, False, False]
    assert got["single"]["shipped"].tolist() == [True, True, False, False, False, True]
    assert got["single_wrong"]["shipped"].tolist() == [False, False, False, False, True, False]
    # foreign frames: accepted at all (every answer wrong)
    assert got["foreign_single"]["shipped"].tolist() == [True, True, False, False, True, True]
    # sequence without a model: the lock rule (mass >= 0.99, then the stay at 0.9)
    assert got["sequence"]["pseudo"].tolist() == [True, True, False, False, False, False]
    tests = aa.sign_tests(got["single"])
    assert set(tests) == {"shipped vs pseudo"}
    assert tests["shipped vs pseudo"]["wins"] == 2 and tests["shipped vs pseudo"]["losses"] == 0


def test_pooled_counts_weigh_routes_by_their_answers(aa):
    rows = [
        {"n": 100, "accepted": 0.5, "precision": 1.0},
        {"n": 300, "accepted": 0.1, "precision": 0.9},
        {"n": 50, "accepted": 0.0, "precision": None},
    ]
    got = aa.pooled_counts(rows)
    assert got["n"] == 450
    assert got["accepted"] == pytest.approx(80 / 450)
    assert got["precision"] == pytest.approx(77 / 80)
    assert aa.pooled_counts([{"n": 10, "accepted": 0.0, "precision": None}])["precision"] is None


def test_parse_cases_reads_route_hierarchy_pairs_and_rejects_the_rest(aa):
    got = aa.parse_cases("nordland_s_w=auto, gp_dl_nr=netvlad-lite1,,gp_dr_nr=x.yaml")
    assert got == [
        ("nordland_s_w", "auto"),
        ("gp_dl_nr", "netvlad-lite1"),
        ("gp_dr_nr", "x.yaml"),
    ]
    for bad in ("", "nordland_s_w", "=auto", "nordland_s_w=", "elsewhere=auto", "a=b,a=b"):
        with pytest.raises(ValueError):
            aa.parse_cases(bad, routes=("a", "nordland_s_w"))


def test_undefined_features_need_a_tier1_global_method_for_the_profile(aa):
    from hmpf.config import parse_config

    def config(tier1: list[str]):
        return parse_config(
            {
                "name": "t",
                "methods": {"sad_w": {"type": "sad", "whiten": 64}},
                "tiers": [{"methods": tier1, "k": 5}, {"methods": ["gist", "sad_w"], "k": 1}],
                "weights": [0.5, 1.0],
            },
            "t",
        )

    seq = ("sequence_logit", "sequence_ref_z", "sequence_agrees", "ref_z")
    glob = config(["sad_w", "gist"])
    assert aa.profile_methods(glob) == ("sad_w", "gist")
    assert aa.undefined_features(seq, glob) == []
    assert aa.undefined_features(("nonsense", "quality"), glob) == ["nonsense"]
    local = config(["kaze"])
    assert aa.profile_methods(local) == ()
    assert aa.undefined_features(seq, local) == ["sequence_ref_z", "ref_z"]


def test_baseline_flags_read_the_shipped_variant_of_a_record(aa):
    kinds = ("single", "single_wrong", "sequence", "sequence_wrong")
    kinds += ("foreign_single", "foreign_sequence")
    flags = {f"{k}:{v}": [1, 0, 1] for k in kinds for v in ("shipped", "pseudo")}
    flags["sequence:shipped"] = [0, 0, 1]
    rec = {"routes": {"gp_dl_nr": {"flags": flags}}}
    got = aa.baseline_flags(rec, "gp_dl_nr")
    assert set(got) == set(kinds)
    assert got["sequence"].tolist() == [False, False, True] and got["sequence"].dtype == bool
    assert aa.baseline_flags(rec, "nordland_s_w") is None
    assert aa.baseline_flags({}, "gp_dl_nr") is None


def test_route_flags_decide_a_variant_on_its_own_answers(aa):
    x = np.array([2.0, 1.0, 0.1])
    correct = np.array([True, True, False])
    hi, lo = np.array([0.995, 0.995, 0.995]), np.array([0.5, 0.5, 0.5])
    base = {m: _answers(x, correct, hi) for m in ("single", "sequence")}
    base |= {f"foreign_{m}": _answers(x, np.zeros(3, bool), hi) for m in ("single", "sequence")}
    other = dict(base) | {"sequence": _answers(x, correct, lo)}
    lock = Policy(model=_model("quality"), model_threshold=0.99)
    got = aa.route_flags({"a": lock, "b": lock}, base, own={"b": other})
    assert got["sequence"]["a"].tolist() == [True, True, False]
    assert got["sequence"]["b"].tolist() == [False, False, False]
    assert got["sequence_wrong"]["a"].tolist() == [False, False, True]
    assert got["single"]["a"].tolist() == got["single"]["b"].tolist()
    assert ("pseudo-seq", "default shipped") in aa.found_pairs()
