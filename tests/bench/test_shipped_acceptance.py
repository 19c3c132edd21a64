"""bench/shipped_acceptance.py's as-decided training figures on synthetic answers."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hmpf.confidence import ConfidenceModel
from hmpf.config import AcceptanceSettings, load_config
from hmpf.errors import HmpfError
from hmpf.evaluation.acceptance import Answers, RoutePart
from hmpf.sequence import Estimate

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sa():
    path = ROOT / "bench" / "shipped_acceptance.py"
    spec = importlib.util.spec_from_file_location("bench_shipped_acceptance", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _answers(sa, correct: np.ndarray, rng: np.random.Generator, shift: float) -> Answers:
    n = len(correct)
    feats = [
        {
            name: float(rng.normal(shift * (2 * c - 1), 1.0))
            for name in sorted({*sa.SEQUENCE_FEATURES, *sa.SINGLE_FEATURES})
        }
        for c in correct
    ]
    ests = [Estimate(i % 50, 0.9, False, i + 1, continuous=i > 0) for i in range(n)]
    return Answers(feats, correct, np.zeros(n), np.arange(n), ests, np.zeros(n, np.int64))


def test_as_decided_gives_each_route_with_and_without_the_stay(sa):
    rng = np.random.default_rng(0)
    parts = []
    for name in ("a", "b", "c"):
        y = rng.random(200) < 0.7
        inside = _answers(sa, y, rng, 1.5)
        outside = _answers(sa, np.zeros(60, bool), rng, 1.5)
        parts.append(RoutePart(name, inside, outside))
    policy, train = sa.fit(parts, parts)
    got = train["sequence"]["as_decided"]
    assert set(got) == {"a", "b", "c"}
    for row in got.values():
        stay, entry = row["with_stay"], row["entry_only"]
        # the stay only keeps accepted estimates on: it accepts at least what entry does
        assert stay["accepted"] >= entry["accepted"]
        assert 0.0 <= entry["outside_accepted"] <= stay["outside_accepted"] <= 1.0
        for fig in (stay, entry):
            assert fig["precision"] is None or 0.0 <= fig["precision"] <= 1.0
    assert policy.sequence_stay_threshold == min(sa.STAY_P, policy.sequence_threshold)


def test_a_recipe_with_the_prior_fits_it_as_an_offset_with_its_stay(sa, tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    parts = []
    for name, prior in (("a", 1.2), ("b", 1.1), ("c", -2.0)):
        y = rng.random(200) < (0.8 if prior > 0 else 0.2)
        inside = _answers(sa, y, rng, 1.5)
        outside = _answers(sa, np.zeros(60, bool), rng, 1.5)
        for f in inside.features + outside.features:
            f["map_prior"] = prior
        parts.append(RoutePart(name, inside, outside))
    recipe = sa.Recipe.of(True, 0.9)
    assert recipe.needs_prior and not sa.Recipe.of(False).needs_prior
    assert recipe.features == (
        (*sa.SINGLE_FEATURES, "map_prior"),
        (*sa.SEQUENCE_FEATURES, "map_prior"),
    )
    policy, _ = sa.fit(parts, parts, recipe.features, recipe.stay)
    for model in (policy.model, policy.sequence_model):
        j = model.features.index("map_prior")
        assert (model.mean[j], model.scale[j], model.coef[j]) == (0.0, 1.0, 1.0)
    assert policy.sequence_stay_threshold == min(0.9, policy.sequence_threshold)
    folds = sa.held_out([(p, p) for p in parts], recipe)
    assert all(f.sequence_model.features == recipe.sequence for f, _ in folds)
    # the recipe a shipped file records is the one model_sets refits the folds with
    monkeypatch.setattr(sa, "ROOT", tmp_path)
    folder = tmp_path / "hmpf" / "presets" / "acceptance"
    folder.mkdir(parents=True)
    assert sa.shipped_recipe("p") == sa.DEFAULT_RECIPE  # no file
    (folder / "p.json").write_text('{"preset": "p"}')
    assert sa.shipped_recipe("p") == sa.DEFAULT_RECIPE  # written before recipes
    (folder / "p.json").write_text(json.dumps({"recipe": recipe.describe()}))
    assert sa.shipped_recipe("p") == recipe
    # a recipe that reads the prior ships the lowest of the routes' priors as the fallback
    priors = (1.2, 1.1, -2.0)
    routes = [SimpleNamespace(name=p.name, map_prior=v) for p, v in zip(parts, priors, strict=True)]
    path = sa.write_shipped("p", load_config("single-tier"), routes, policy, recipe)
    doc = json.loads(path.read_text())
    assert doc["recipe"] == recipe.describe()
    assert doc["sequence"] == dict(load_config("single-tier").sequence or {})  # the filter read
    assert AcceptanceSettings(**doc["acceptance"]).map_prior_fallback == -2.0
    assert sa.shipped_recipe("p") == recipe
    plain = sa.write_shipped("p", load_config("single-tier"), routes, policy, sa.DEFAULT_RECIPE)
    assert "map_prior_fallback" not in json.loads(plain.read_text())["acceptance"]


def test_a_gated_recipe_fits_each_model_asked_with_its_gate(sa, tmp_path, monkeypatch):
    from hmpf.evaluation.acceptance import _pooled  # the rows a pooled fit reads

    rng = np.random.default_rng(4)
    parts = []
    for name, prior in (("a", 1.2), ("b", 1.1), ("c", -2.0)):
        inside = _answers(sa, rng.random(200) < 0.7, rng, 1.5)
        outside = _answers(sa, np.zeros(60, bool), rng, -0.5)
        for f in inside.features + outside.features:
            f["map_prior"] = prior
        parts.append(RoutePart(name, inside, outside))
    for f in (x for p in parts for a in (p.answers, p.outside) for x in a.features):
        f["ref_z_low"] = min(f["ref_z"], 0.0)
    recipe = sa.Recipe.of(True, 0.9, gate=("single",), single_share=0.2, single_extra=["ref_z_low"])
    assert recipe.single == (*sa.SINGLE_FEATURES, "ref_z_low", "map_prior")
    assert recipe.single_extra == ("ref_z_low",) and sa.Recipe.of(True).single_extra == ()
    assert recipe.describe()["gate"] == ["single"] and recipe.describe()["single_share"] == 0.2
    assert not {"gate", "single_share"} & set(sa.Recipe.of(True).describe())
    policy, _ = sa.fit_recipe([(p, p) for p in parts], recipe)
    assert policy.sequence_model is not None and policy.sequence_model.gate is None
    model = policy.model
    assert model is not None and model.gate is not None
    assert "map_prior" not in model.gate.features  # the prior is not evidence of being in it
    # the same as fitting the pooled rows' gate and in-map model by hand
    X, y, w, _, inside = _pooled(parts, recipe.single, 0.2)  # the recipe's share
    want = ConfidenceModel.fit_gated(
        X, y, recipe.single, inside, sample_weight=w, offsets=["map_prior"]
    )
    np.testing.assert_allclose(model.predict(X), want.predict(X), rtol=1e-12)
    # the shipped file records the gate, and the folds are refitted with it
    monkeypatch.setattr(sa, "ROOT", tmp_path)
    folder = tmp_path / "hmpf" / "presets" / "acceptance"
    folder.mkdir(parents=True)
    (folder / "p.json").write_text(json.dumps({"recipe": recipe.describe()}))
    assert sa.shipped_recipe("p") == recipe
    assert all(f.model.gate is not None for f, _ in sa.held_out([(p, p) for p in parts], recipe))
    assert sa.gate_models("single,sequence") == ("single", "sequence")
    assert sa.gate_models("none") == ()
    with pytest.raises(SystemExit, match="unknown"):
        sa.gate_models("tier1")
    assert sa.single_extra("ref_z_low, tier1_z") == ("ref_z_low", "tier1_z")
    for bad in ("ref_z", "sequence_ref_z", "speed"):
        with pytest.raises(SystemExit, match="not an extra"):
            sa.single_extra(bad)


def test_filter_settings_are_tried_over_the_preset(sa):
    config = load_config("default")
    tried = sa.with_filter(config, ["combined_weight=1.0", "max_steps=3"])
    assert tried.sequence_params().combined_weight == 1.0
    assert tried.sequence_params().max_steps == 3
    assert isinstance(tried.sequence["max_steps"], int)
    # the other settings stay the preset's, and so does its digest (the filter stores none)
    assert tried.sequence_params().stop_factor == config.sequence_params().stop_factor
    assert tried.digest() == config.digest()
    assert sa.with_filter(config, []) is config
    for bad in (["combined_weight"], ["nope=1"], ["combined_weight=x"]):
        with pytest.raises(SystemExit, match="--filter"):
            sa.with_filter(config, bad)
    with pytest.raises(HmpfError, match="weights must be >= 0"):
        sa.with_filter(config, ["combined_weight=-1"])


def test_a_recipes_stay_floor_reaches_the_policy_and_the_shipped_file(sa, tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    parts = [
        RoutePart(
            n,
            _answers(sa, rng.random(200) < 0.7, rng, 1.5),
            _answers(sa, np.zeros(60, bool), rng, -0.5),
        )
        for n in ("a", "b")
    ]
    recipe = sa.Recipe.of(False, 0.9, stay_ref_z=-0.75)
    assert recipe.describe()["stay_ref_z"] == -0.75
    assert "stay_ref_z" not in sa.Recipe.of(False, 0.9).describe()
    policy, train = sa.fit_recipe([(p, p) for p in parts], recipe)
    assert policy.sequence_stay_ref_z == -0.75
    # the training drives decided with the floor (as_decided reads each answer's support)
    assert set(train["sequence"]["as_decided"]) == {"a", "b"}
    monkeypatch.setattr(sa, "ROOT", tmp_path)
    (tmp_path / "hmpf" / "presets" / "acceptance").mkdir(parents=True)
    routes = [SimpleNamespace(name=p.name, map_prior=None) for p in parts]
    path = sa.write_shipped("p", load_config("single-tier"), routes, policy, recipe)
    doc = json.loads(path.read_text())
    settings = AcceptanceSettings(**doc["acceptance"])
    assert settings.sequence_stay_ref_z == -0.75 and "at least -0.75" in settings.note
    assert sa.shipped_recipe("p") == recipe
    assert sa.stay_floor("none") is None and sa.stay_floor("-0.5") == -0.5
    for bad in ("inf", "nan", "x"):
        with pytest.raises(ValueError, match="stay-ref-z"):
            sa.stay_floor(bad)
