"""The one acceptance policy (:mod:`hmpf.acceptance`): the rules, hysteresis, off the map, the
shipped models of the bundled presets, and that evaluation decides through the same code."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from hmpf.acceptance import DEFAULT_ACCEPT_THRESHOLD, Decision, Policy
from hmpf.confidence import ConfidenceModel, ModelError, answer_features
from hmpf.config import (
    AcceptanceSettings,
    ConfigError,
    load_config,
    parse_config,
    preset_names,
    shipped_acceptance,
    with_shipped_acceptance,
)
from hmpf.evaluation.acceptance import Answers, apply_acceptance, decide
from hmpf.hierarchy import HierarchyResult, TierResult
from hmpf.sequence import Estimate, RouteMap

ROUTES = RouteMap.from_metadata(12)


def _result(match: int, quality: float, n: int = 12) -> HierarchyResult:
    """A two-method, one-tier result peaked at ``match`` (raw scores too)."""
    s = np.linspace(0.0, 0.5, n)
    s[match] = 1.0
    tier = TierResult(["a", "b"], None, {"a": s, "b": s}, np.array([match, (match + 5) % n]),
                      0.1, {"a": s, "b": s})  # fmt: skip
    return HierarchyResult(
        match, quality, np.array([match, (match + 5) % n]), np.array([quality, -quality]), [tier]
    )


def _model(names: tuple[str, ...], coef: float = 1.0) -> ConfidenceModel:
    k = len(names)
    return ConfidenceModel(names, (0.0,) * k, (1.0,) * k, (coef,) * k, 0.0)


def _estimate(ref: int = 3, mass: float = 0.95, **extra: object) -> Estimate:
    est = Estimate(ref, mass, mass >= 0.99, 10, 1.0)
    return replace(est, **extra) if extra else est


# -- single frame -------------------------------------------------------------------------------


def test_without_a_model_the_quality_rule_decides_with_the_default_threshold() -> None:
    policy = Policy.of(None)
    assert policy.threshold == DEFAULT_ACCEPT_THRESHOLD and policy.single_rule == "quality"
    hi = policy.single(_result(4, DEFAULT_ACCEPT_THRESHOLD + 0.1), ROUTES)
    lo = policy.single(_result(4, DEFAULT_ACCEPT_THRESHOLD - 0.1), ROUTES)
    assert hi == Decision(True, "quality", None, value=pytest.approx(3.0))
    assert not lo.accepted and lo.p_correct is None
    # a threshold from the settings, overridden by the caller's
    settings = AcceptanceSettings(threshold=1.0)
    assert Policy.of(settings).single(_result(4, 1.5), ROUTES).accepted
    assert not Policy.of(settings, threshold=2.0).single(_result(4, 1.5), ROUTES).accepted


def test_a_match_without_a_finite_score_or_no_match_is_never_accepted() -> None:
    model = _model(("quality",))
    policy = Policy(threshold=-10.0, model=model, model_threshold=0.0)
    for result in (_result(4, math.nan), HierarchyResult(-1, math.nan, np.zeros(0, int),
                                                          np.zeros(0))):  # fmt: skip
        d = policy.single(result, ROUTES)
        assert not d.accepted and d.p_correct is None and d.accepted_by == "p_correct"
    assert not Policy(threshold=-10.0).single(_result(4, math.nan), ROUTES).accepted


def test_with_a_model_p_correct_is_the_models_probability_of_the_answers_features() -> None:
    names = ("quality", "agreement", "tier1_margin")
    model = ConfidenceModel(names, (1.0, 0.5, 0.1), (2.0, 0.5, 0.2), (1.5, 0.5, 2.0), -0.3)
    policy = Policy(model=model, model_threshold=0.6)
    result = _result(7, 2.2)
    d = policy.single(result, ROUTES)
    p = model.predict(answer_features(result, ROUTES))
    assert d.p_correct == pytest.approx(p) and d.accepted == (p >= 0.6)
    assert d.accepted_by == "p_correct"


def test_policy_refuses_a_single_frame_model_over_sequence_features() -> None:
    seq = _model(("sequence_logit",))
    settings = AcceptanceSettings(threshold=1.0, model=seq.to_dict(), model_threshold=0.5)
    with pytest.raises(ModelError, match="sequence_logit"):
        Policy.of(settings)


def test_evaluation_decides_through_the_policy() -> None:
    """apply_acceptance's decisions are Policy.single's on the same results."""
    names = ("quality", "agreement")
    policy = Policy(model=_model(names, 0.8), model_threshold=0.7)
    results = [_result(i, q) for i, q in zip(range(10), np.linspace(-1, 3, 10), strict=True)]
    answers = Answers(
        [answer_features(r, ROUTES) for r in results],
        np.ones(10, bool),
        np.array([r.quality for r in results]),
        np.arange(10),
    )
    rep = apply_acceptance(policy, answers)
    direct = [policy.single(r, ROUTES) for r in results]
    assert rep["accepted_answers"] == [d.accepted for d in direct]
    assert rep["p_correct"] == pytest.approx([d.p_correct for d in direct])
    assert rep["rule"] == "p_correct" and 0 < rep["accepted"] < 1


# -- sequence mode ------------------------------------------------------------------------------


def test_lock_rule_with_hysteresis() -> None:
    policy = Policy.of(None, lock_mass=0.99)
    assert policy.unlock_mass < policy.lock_mass and policy.sequence_rule == "lock"
    fresh = _estimate(mass=0.95)
    assert not policy.sequence_from(None, fresh, held=False).accepted
    cont = _estimate(mass=0.95, continuous=True)
    assert policy.sequence_from(None, cont, held=True).accepted  # held and continuous: stays
    jumped = _estimate(mass=0.95, continuous=False)
    assert not policy.sequence_from(None, jumped, held=True).accepted  # moved away: must re-lock
    low = _estimate(mass=policy.unlock_mass - 0.01, continuous=True)
    assert not policy.sequence_from(None, low, held=True).accepted
    assert policy.sequence_from(None, _estimate(mass=0.995), held=False).accepted
    # the filter's own flag is read when the caller does not say
    assert policy.sequence_from(None, _estimate(mass=0.95, continuous=True, held=True)).accepted


def test_off_the_map_is_never_accepted_and_says_so() -> None:
    policy = Policy.of(None)
    d = policy.sequence_from(None, _estimate(mass=1.0, off_map=0.7), held=True)
    assert not d.accepted and d.off_map
    d = policy.sequence_from(None, _estimate(mass=1.0, off_map=0.2))
    assert d.accepted and not d.off_map


def test_sequence_model_with_stay_threshold() -> None:
    names = ("sequence_logit",)
    model = _model(names, 0.25)
    policy = Policy(sequence_model=model, sequence_threshold=0.9, sequence_stay_threshold=0.6)
    feats = {"sequence_logit": 4.0}  # p = sigmoid(1) = 0.73
    est = _estimate(continuous=True)
    assert not policy.sequence_from(feats, est, held=False).accepted
    held = policy.sequence_from(feats, est, held=True)
    assert held.accepted and held.p_correct == pytest.approx(1 / (1 + math.exp(-1)))
    assert not policy.sequence_from(feats, replace(est, continuous=False), held=True).accepted
    assert (
        not replace(policy, sequence_stay_threshold=None)
        .sequence_from(feats, est, held=True)
        .accepted
    )


def _floor_policy() -> Policy:
    """A sequence model (``p = sigmoid(sequence_logit / 4)``), entry 0.9, stay 0.6, floor -0.75."""
    return Policy(
        sequence_model=_model(("sequence_logit",), 0.25),
        sequence_threshold=0.9,
        sequence_stay_threshold=0.6,
        sequence_stay_ref_z=-0.75,
    )


def test_the_stay_threshold_needs_the_frames_own_support_above_its_floor() -> None:
    policy = _floor_policy()
    est = _estimate(continuous=True)
    feats = {"sequence_logit": 4.0}  # p = 0.73: between the stay and the entry thresholds
    for z, stays in ((0.3, True), (-0.75, True), (-0.76, False), (-3.0, False), (math.nan, False)):
        got = policy.sequence_from({**feats, "sequence_ref_z": z}, est, held=True)
        assert got.accepted is stays, z
        assert got.p_correct == pytest.approx(1 / (1 + math.exp(-1)))
    # below the floor the entry threshold still decides: a sure estimate stays accepted
    sure = {"sequence_logit": 12.0, "sequence_ref_z": -3.0}  # p = 0.95
    assert policy.sequence_from(sure, est, held=True).accepted
    # no floor: as before; a floor without the feature is a clear error, never a guess
    low = {**feats, "sequence_ref_z": -3.0}
    assert replace(policy, sequence_stay_ref_z=None).sequence_from(low, est, held=True).accepted
    with pytest.raises(ModelError, match="sequence_ref_z"):
        policy.sequence_from(feats, est, held=True)
    # an unheld frame never reads it (the entry threshold decides)
    assert not policy.sequence_from(feats, est, held=False).accepted
    assert policy.needs_profile and not replace(policy, sequence_stay_ref_z=None).needs_profile


def test_a_frame_held_back_by_the_floor_alone_keeps_the_lock() -> None:
    policy = _floor_policy()
    est = _estimate(continuous=True)
    weak = {"sequence_logit": 4.0, "sequence_ref_z": -3.0}  # p = 0.73, below the floor
    d = policy.sequence_from(weak, est, held=True)
    assert not d.accepted and d.kept and d.holds
    # accepted frames hold without being "kept"; a supported frame is simply accepted
    ok = policy.sequence_from({**weak, "sequence_ref_z": 0.0}, est, held=True)
    assert ok.accepted and not ok.kept and ok.holds
    # nothing is kept: below the stay threshold, unheld, not continuous, off the map,
    # without a floor
    low = {"sequence_logit": 0.0, "sequence_ref_z": -3.0}  # p = 0.44 < 0.6
    assert not policy.sequence_from(low, est, held=True).holds
    assert not policy.sequence_from(weak, est, held=False).holds
    assert not policy.sequence_from(weak, replace(est, continuous=False), held=True).holds
    off = policy.sequence_from(weak, replace(est, off_map=0.3), held=True)
    assert not off.accepted and not off.holds and not off.off_map  # p 0.51 < 0.6
    gone = policy.sequence_from(
        {"sequence_logit": 40.0, "sequence_ref_z": -3.0}, replace(est, off_map=0.6), held=True
    )
    assert gone.off_map and not gone.holds
    no_floor = replace(policy, sequence_stay_ref_z=None)
    assert not no_floor.sequence_from(low, est, held=True).kept


def test_decide_carries_a_kept_lock_to_the_next_frame() -> None:
    policy = _floor_policy()
    sure = {"sequence_logit": 12.0, "sequence_ref_z": 1.0}  # p = 0.95: enters
    weak = {"sequence_logit": 4.0, "sequence_ref_z": -3.0}  # p = 0.73, unsupported
    mid = {"sequence_logit": 4.0, "sequence_ref_z": 1.0}  # p = 0.73, supported
    feats = [sure, weak, mid, weak, weak, mid]
    ests = [_estimate(continuous=True) for _ in feats]
    answers = Answers(
        feats, np.ones(6, bool), np.zeros(6), np.arange(6), ests, np.zeros(6, np.int64)
    )
    got = [d.accepted for d in decide(policy, answers, sequence=True)]
    # the weak frames are not accepted, but the lock carries over them: the supported frame
    # after them stays at the stay threshold instead of needing the entry threshold
    assert got == [True, False, True, False, False, True]


def test_decide_carries_the_decision_from_frame_to_frame_within_a_drive() -> None:
    policy = Policy.of(None)
    masses = [0.995, 0.95, 0.95, 0.95, 0.995, 0.95]
    ests = [_estimate(mass=m, continuous=True) for m in masses]
    answers = Answers(
        [{} for _ in ests], np.ones(6, bool), np.array(masses), np.arange(6), ests,
        np.array([0, 0, 0, 1, 1, 1]),
    )  # fmt: skip
    got = [d.accepted for d in decide(policy, answers, sequence=True)]
    # drive 0: locks, then held; drive 1 starts unheld: 0.95 is not enough until it locks
    assert got == [True, True, True, False, True, True]
    with pytest.raises(ModelError):
        decide(policy, Answers([{}], np.ones(1, bool), np.ones(1), np.zeros(1)), sequence=True)


def test_stay_threshold_settings_are_validated() -> None:
    seq = _model(("sequence_logit",)).to_dict()
    ok = AcceptanceSettings(
        threshold=1.0, sequence_model=seq, sequence_threshold=0.9, sequence_stay_threshold=0.5
    )
    assert Policy.of(ok).sequence_stay_threshold == 0.5
    with pytest.raises(ValueError, match="must not exceed"):
        AcceptanceSettings(
            threshold=1.0, sequence_model=seq, sequence_threshold=0.5, sequence_stay_threshold=0.9
        )
    with pytest.raises(ValueError, match="needs a sequence_model"):
        AcceptanceSettings(threshold=1.0, sequence_stay_threshold=0.5)
    floor = ok.model_copy(update={"sequence_stay_ref_z": -0.75})
    floor = AcceptanceSettings.model_validate(floor.model_dump())
    assert floor.needs_profile and not ok.needs_profile
    assert Policy.of(floor).sequence_stay_ref_z == -0.75
    assert Policy.of(floor).describe()["sequence_model"]["stay_ref_z"] == -0.75
    with pytest.raises(ValueError, match="needs a sequence_stay_threshold"):
        AcceptanceSettings(
            threshold=1.0, sequence_model=seq, sequence_threshold=0.9, sequence_stay_ref_z=-1.0
        )
    with pytest.raises(ValueError):
        AcceptanceSettings.model_validate({**floor.model_dump(), "sequence_stay_ref_z": math.inf})


# -- shipped models -----------------------------------------------------------------------------


def test_shipped_models_are_matched_by_the_hierarchys_digest() -> None:
    shipped = shipped_acceptance()
    assert shipped, "the bundled presets ship confidence models"
    default = load_config("default")
    assert default.acceptance is not None and default.acceptance.model is not None
    assert default.acceptance == shipped[default.digest()]
    # the same hierarchy from a file gets it too; an edited one does not (no stale model)
    raw = default.model_dump(exclude={"acceptance"})
    assert with_shipped_acceptance(parse_config(raw)).acceptance == default.acceptance
    edited = parse_config({**raw, "weights": [0.25, 1.0]})
    assert with_shipped_acceptance(edited).acceptance is None
    # a config's own acceptance (hmpf-calibrate's) wins
    own = parse_config({**raw, "acceptance": {"threshold": 1.5}})
    assert with_shipped_acceptance(own).acceptance == AcceptanceSettings(threshold=1.5)


def test_shipped_models_bring_the_filter_settings_they_were_fitted_under() -> None:
    default = load_config("default")
    preset_filter = default.sequence_params()
    raw = default.model_dump(exclude={"acceptance"})
    # an index built before the preset's filter weighed motion stored no filter settings
    old = parse_config({**raw, "sequence": None})
    assert preset_filter.motion and not old.sequence_params().motion
    got = with_shipped_acceptance(old)
    assert got.acceptance == default.acceptance
    assert got.sequence_params() == preset_filter
    assert got.digest() == default.digest()
    # a setting the config makes itself stays its own; the others come with the models
    own = parse_config({**raw, "sequence": {"moved": 0.5, "combined_weight": 3.0}})
    mine = with_shipped_acceptance(own).sequence_params()
    assert (mine.moved, mine.combined_weight) == (0.5, 3.0)
    assert mine.stop_factor == preset_filter.stop_factor
    # with its own acceptance (hmpf-calibrate's models) the config's filter is left alone
    calibrated = parse_config({**raw, "sequence": None, "acceptance": {"threshold": 1.5}})
    assert with_shipped_acceptance(calibrated).sequence is None


def test_every_shipped_model_loads_and_names_its_preset(tmp_path) -> None:
    from importlib.resources import files

    folder = files("hmpf").joinpath("presets", "acceptance")
    names = set(preset_names())
    for entry in folder.iterdir():
        if not entry.name.endswith(".json"):
            continue
        doc = json.loads(entry.read_text())
        assert doc["preset"] in names
        config = load_config(doc["preset"])
        assert config.digest() == doc["digest"], f"{entry.name} is stale: refit it"
        policy = Policy.of(config.acceptance)
        assert policy.model is not None and policy.sequence_model is not None
        assert 0 < policy.model_threshold <= 1 and 0 < policy.sequence_threshold <= 1


def test_a_corrupt_shipped_file_is_a_clear_error(monkeypatch, tmp_path) -> None:
    import hmpf.config as cfg

    (tmp_path / "acceptance").mkdir()
    (tmp_path / "acceptance" / "x.json").write_text('{"digest": "d", "acceptance": {}}')
    monkeypatch.setattr(cfg, "_presets_dir", lambda: tmp_path)
    with pytest.raises(ConfigError, match="x.json"):
        shipped_acceptance()


def test_a_shipped_files_own_filter_settings_win_over_its_presets(monkeypatch, tmp_path) -> None:
    import shutil

    import hmpf.config as cfg

    presets = tmp_path / "presets"
    shutil.copytree(cfg._presets_dir(), presets)  # type: ignore[arg-type]
    monkeypatch.setattr(cfg, "_presets_dir", lambda: presets)
    default = load_config("default")
    shipped = presets / "acceptance" / "default.json"
    doc = json.loads(shipped.read_text())
    assert "sequence" not in doc or doc["sequence"] == default.sequence
    doc["sequence"] = {"combined_weight": 1.0}  # the filter a refit read, recorded with it
    shipped.write_text(json.dumps(doc))
    old = parse_config({**default.model_dump(exclude={"acceptance"}), "sequence": None})
    got = with_shipped_acceptance(old).sequence_params()
    assert got.combined_weight == 1.0 and not got.motion
