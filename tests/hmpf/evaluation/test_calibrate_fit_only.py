"""``hmpf-calibrate --config NAME --fit-only``: the acceptance of a given hierarchy, no search."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from hmpf.config import AcceptanceSettings, load_config, parse_config
from hmpf.datasets import frame_ground_truth, list_images
from hmpf.errors import ConfigError
from hmpf.evaluation.calibrate import (
    SearchSpace,
    _carry_stay,
    calibrate,
    fit_config_acceptance,
    fit_only,
)
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import CostModel, ScoreBank, split_data
from hmpf.features import FeatureCache
from tests.conftest import link_route

POOL = {"name": "fit-only-pool", "tiers": [{"methods": ["hog", "gist", "sad"], "k": 1}]}
#: A hierarchy someone already runs: its own name, index settings, sequence settings and a
#: stale acceptance that the fit replaces.
GIVEN = """\
name: given
description: a hierarchy already in service
tiers:
  - {methods: [hog, gist], k: 5}
  - {methods: [sad], k: 1}
index:
  faiss: {"*": Flat}
sequence: {lock_mass: 0.5}
acceptance: {threshold: 99.0, note: stale}
"""
N_IMAGES = 60  # per traverse: blocks of 10 -> 30 training and 30 test frames
COSTS = CostModel(  # fixed: the search path measures nothing
    units={f"extract:{m}": 1.0 for m in ("hog", "gist", "sad")},
    method_units={m: [f"extract:{m}"] for m in ("hog", "gist", "sad")},
    match={m: (0.0, 0.001) for m in ("hog", "gist", "sad")},
    fusion_ms=0.01,
    n_db=30,
)


@pytest.fixture(scope="module")
def route(gardens_point: Path, gp_feature_cache: Path, tmp_path_factory: pytest.TempPathFactory):
    """The first 60 frames of day_right -> night_right (symlinked, for the command), the
    split's parts, its feature cache and the pool's training bank."""
    root = tmp_path_factory.mktemp("route")
    sub = link_route(gardens_point, root, N_IMAGES)
    cache_dir = gp_feature_cache
    cache = FeatureCache(cache_dir)
    refs, qrys = list_images(sub["day_right"]), list_images(sub["night_right"])
    data = EvalData(refs, qrys, frame_ground_truth(N_IMAGES, N_IMAGES, 2), "frames +-2")
    parts = split_data(data, scheme="blocks", block=10)
    pool = parse_config(POOL)
    train = ScoreBank.build(pool, parts[0], cache=cache, workers=2)
    return {"sub": sub, "cache_dir": cache_dir, "cache": cache, "parts": parts, "pool": pool}, train


def _argv(route: dict, config: Path, out: Path, *extra: str) -> list[str]:
    sub = route["sub"]
    return [
        "--quiet", "--reference", str(sub["day_right"]), "--query", str(sub["night_right"]),
        "--tolerance", "2", "--block", "10", "--cache-dir", str(route["cache_dir"]),
        "--workers", "2", "--target-precision", "0.9", "--config", str(config),
        "--out", str(out), *extra,
    ]  # fmt: skip


def test_fit_only_writes_the_given_config_with_a_fitted_acceptance(route, tmp_path, capsys):
    """The written config is the given one with only its acceptance replaced: it loads, its
    models load, its thresholds are probabilities and its digest is the input's."""
    from hmpf.cli import calibrate as cli
    from hmpf.confidence import ConfidenceModel
    from hmpf.evaluation.acceptance import SINGLE_FEATURES

    info, _ = route
    given_file = tmp_path / "given.yaml"
    given_file.write_text(GIVEN)
    given = load_config(given_file)
    out = tmp_path / "out"
    assert cli.main([*_argv(info, given_file, out), "--fit-only"]) == 0
    written = load_config(out / "calibrated.yaml")
    assert written.digest() == given.digest()
    # Everything but the acceptance is as given (name, index and sequence settings too).
    assert written.model_copy(update={"acceptance": None}) == given.model_copy(
        update={"acceptance": None}
    )
    acc = written.acceptance
    assert acc is not None and acc.precision == 0.9
    assert acc.threshold != 99.0 and acc.note != "stale"
    assert AcceptanceSettings.model_validate(acc.model_dump()) == acc
    assert acc.model is not None and acc.model_threshold is not None
    assert 0 <= acc.model_threshold <= 1
    model = ConfidenceModel.from_dict(acc.model, expected=SINGLE_FEATURES)
    assert model.features == SINGLE_FEATURES
    assert acc.sequence_model is None  # no --sequence: no sequence model
    rep = json.loads((out / "calibration.json").read_text())
    assert rep["mode"] == "fit-only" and rep["digest"] == given.digest()
    assert rep["protocol"]["config"] == str(given_file)
    assert rep["protocol"]["ground_truth"] == "frames +-2"
    assert "winner" not in rep["train"] and "leaderboard" not in rep["train"]
    assert rep["train"]["n_query"] == 30 and rep["test"]["n_query"] == 30
    assert acc.threshold == pytest.approx(rep["train"]["acceptance"]["threshold"], abs=1e-6)
    assert rep["train"]["confidence"]["single"]["threshold"] == acc.model_threshold
    # The test part measured as the search's winner's is, less the (unmeasured) cost model.
    te = rep["test"]
    assert te["best_single"] in given.method_ids and "model_ms" not in te
    assert te["confidence"]["single"]["model"]["n"] == 30
    board = (out / "leaderboard.md").read_text()
    assert "Fit only" in board and given.digest()[:16] in board and "| rank |" not in board
    header = (out / "calibrated.yaml").read_text().splitlines()[:3]
    assert any("--fit-only" in line for line in header)
    assert any(given.digest() in line for line in header)
    assert "Fit only" in capsys.readouterr().out


def test_fit_only_fits_what_the_search_fits_for_its_winner(route):
    """The search's winner, given back as a config and scored alone (as the command scores
    a given config), gets the same z threshold, filter settings and models from fit_only."""
    info, train = route
    pool = info["pool"]
    space = SearchSpace(tuple(pool.method_ids), max_tiers=2, max_per_tier=1, k1=(5,), refine=1)
    searched, rep = calibrate(
        pool,
        train,
        None,
        space,
        budget_ms=None,
        target_precision=0.9,
        costs=COSTS,
        sequence=True,
    )
    assert searched.acceptance is not None and searched.acceptance.model is not None
    given = searched.model_copy(update={"acceptance": None, "sequence": None})
    own_train = ScoreBank.build(given, info["parts"][0], cache=info["cache"])
    assert set(own_train.methods) == set(given.method_ids) < set(train.methods)
    fitted, rep2 = fit_only(given, own_train, None, target_precision=0.9, sequence=True)
    assert fitted == searched  # acceptance (models, thresholds) and sequence: settings
    assert fitted.digest() == given.digest() == rep2["digest"]
    for key in ("acceptance", "sequence", "confidence"):
        assert rep2["train"][key] == rep["train"][key], key
    assert rep2["train"]["recall_at_1"] == rep["train"]["winner"]["recall_at_1"]
    # Without models the whole acceptance is replaced: no model of the input survives.
    plain = fit_config_acceptance(fitted, own_train, target_precision=0.9, model=False)
    assert plain.config.acceptance is not None and plain.config.acceptance.model is None
    assert plain.config.acceptance.threshold == fitted.acceptance.threshold
    assert plain.config.sequence == fitted.sequence and plain.confidence is None


def test_fit_only_keeps_the_given_models_off_map_terms(route):
    """A given config whose single-frame model has staged off-map hinges (as the shipped
    default's): the route's own model fits its features as without and keeps the hinges'
    coefficients as they were; the report and leaderboard say so. ``outside=False`` (no
    off-map answers, ``--no-outside``) keeps nothing of them."""
    from hmpf.confidence import ConfidenceModel
    from hmpf.evaluation.acceptance import SINGLE_FEATURES
    from hmpf.evaluation.calibrate import leaderboard_markdown

    info, train = route
    hinges = {"ref_z_low": 0.4, "cand_z_low": 1.5}
    stale = ConfidenceModel(SINGLE_FEATURES, (0.0,) * 4, (1.0,) * 4, (1.0,) * 4, 0.0)
    acc = AcceptanceSettings(
        threshold=99.0, model=stale.with_terms(hinges).to_dict(), model_threshold=0.5
    )
    given = parse_config(yaml.safe_load(GIVEN)).model_copy(update={"acceptance": acc})
    bare = given.model_copy(update={"acceptance": None})
    kept = fit_config_acceptance(given, train, target_precision=0.9)
    plain = fit_config_acceptance(bare, train, target_precision=0.9)
    assert kept.config.acceptance is not None and plain.config.acceptance is not None
    km = ConfidenceModel.from_dict(kept.config.acceptance.model)
    pm = ConfidenceModel.from_dict(plain.config.acceptance.model)
    assert pm.features == SINGLE_FEATURES and km == pm.with_terms(hinges)
    assert kept.confidence is not None and kept.confidence["single"]["carried"] == hinges
    assert "carried" not in (plain.confidence or {})["single"]
    none = fit_config_acceptance(given, train, target_precision=0.9, outside=False)
    assert none.config.acceptance is not None
    assert ConfidenceModel.from_dict(none.config.acceptance.model).features == SINGLE_FEATURES
    fitted, rep = fit_only(given, train, None, target_precision=0.9)
    assert fitted.acceptance == kept.config.acceptance
    assert "off-map terms as they were (ref_z_low 0.400, cand_z_low 1.500)" in (
        leaderboard_markdown(rep)
    )


def test_fit_only_with_sequence_keeps_the_given_stay_threshold(route):
    """A given config with a sequence stay threshold and evidence floor (as the shipped
    default's): the route's own sequence model gets them (the threshold at most the fitted
    entry threshold), the report and leaderboard say so; a given config without them gets
    none, and so does a fit without models."""
    from hmpf.confidence import ConfidenceModel
    from hmpf.evaluation.acceptance import SEQUENCE_MODEL_FEATURES, SINGLE_FEATURES
    from hmpf.evaluation.calibrate import leaderboard_markdown

    info, train = route
    single = ConfidenceModel(SINGLE_FEATURES, (0.0,) * 4, (1.0,) * 4, (1.0,) * 4, 0.0)
    seq = ConfidenceModel(SEQUENCE_MODEL_FEATURES, (0.0,) * 3, (1.0,) * 3, (1.0,) * 3, 0.0)
    acc = AcceptanceSettings(
        threshold=99.0,
        model=single.to_dict(),
        model_threshold=0.5,
        sequence_model=seq.to_dict(),
        sequence_threshold=0.999,
        sequence_stay_threshold=0.9,
        sequence_stay_ref_z=-0.5,
    )
    # one weak method, so that the training drive has wrong estimates to fit on
    weak = {**yaml.safe_load(GIVEN), "tiers": [{"methods": ["sad"], "k": 1}]}
    given = parse_config(weak).model_copy(update={"acceptance": acc})
    fitted, rep = fit_only(given, train, None, target_precision=0.9, sequence=True)
    got = fitted.acceptance
    assert got is not None and got.sequence_model is not None, rep["train"]["confidence"]
    assert got.sequence_model != seq.to_dict()  # refitted on the route
    assert got.sequence_threshold is not None
    assert got.sequence_stay_threshold == min(0.9, got.sequence_threshold)
    assert got.sequence_stay_ref_z == -0.5
    stay = rep["train"]["confidence"]["sequence"]["stay"]
    assert (stay["threshold"], stay["ref_z"]) == (got.sequence_stay_threshold, -0.5)
    # the training drives as the policy decides them, the stay included
    d = stay["as_decided"]
    assert 0 <= d["accepted"] <= 1 and d["n"] == rep["train"]["confidence"]["sequence"]["n"]
    assert d["rule"] == "p_correct" and d["threshold"] == got.sequence_threshold
    board = leaderboard_markdown(rep)
    assert "keeps the given config's stay threshold" in board
    assert f"accepted {d['accepted']:.3f}" in board
    # a given stay above the route's entry threshold: capped at it (the step alone)
    low = got.model_copy(
        update={
            "sequence_threshold": 0.8,
            "sequence_stay_threshold": None,
            "sequence_stay_ref_z": None,
        }
    )
    figures: dict = {}
    capped = _carry_stay(fitted.model_copy(update={"acceptance": low}), acc, figures).acceptance
    assert capped is not None and capped.sequence_threshold == 0.8
    assert capped.sequence_stay_threshold == 0.8 and capped.sequence_stay_ref_z == -0.5
    assert figures["sequence"]["stay"] == {"threshold": 0.8, "ref_z": -0.5}
    # no sequence model fitted (a training drive all right or all wrong): no stay threshold
    no_seq = got.model_copy(
        update={
            "sequence_model": None,
            "sequence_threshold": None,
            "sequence_stay_threshold": None,
            "sequence_stay_ref_z": None,
        }
    )
    figures = {}
    kept = _carry_stay(fitted.model_copy(update={"acceptance": no_seq}), acc, figures)
    assert kept.acceptance == no_seq and figures == {}
    # the given config without a stay threshold: none
    bare = given.model_copy(
        update={
            "acceptance": acc.model_copy(
                update={"sequence_stay_threshold": None, "sequence_stay_ref_z": None}
            )
        }
    )
    plain, rep2 = fit_only(bare, train, None, target_precision=0.9, sequence=True)
    assert plain.acceptance is not None and plain.acceptance.sequence_stay_threshold is None
    assert "stay" not in rep2["train"]["confidence"]["sequence"]
    assert plain.acceptance.sequence_model == got.sequence_model
    # no models: nothing to carry
    nomodel = fit_config_acceptance(given, train, target_precision=0.9, sequence=True, model=False)
    assert nomodel.config.acceptance is not None
    assert nomodel.config.acceptance.sequence_stay_threshold is None


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--fit-only"], "--fit-only needs --config"),
        (["--config", "handcrafted"], "--config is only read with --fit-only"),
        (["--fit-only", "--config", "handcrafted", "--name", "x"], "--name not with --fit-only"),
        (["--fit-only", "--config", "handcrafted", "--methods", "hog"], "--methods not with"),
    ],
)
def test_fit_only_flag_errors_exit_2_as_argparse(extra, message, tmp_path, capsys):
    from hmpf.cli import calibrate as cli

    argv = ["--reference", str(tmp_path), "--query", str(tmp_path), "--out", str(tmp_path / "o")]
    with pytest.raises(SystemExit) as exc:
        cli.main([*argv, *extra])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and message in err and err.startswith("usage: hmpf-calibrate")
    assert not (tmp_path / "o").exists()


def test_fit_only_unreadable_config_is_one_line(tmp_path, capsys):
    from hmpf.cli import calibrate as cli

    argv = [
        "--reference", str(tmp_path), "--query", str(tmp_path), "--out", str(tmp_path / "o"),
        "--fit-only", "--config", str(tmp_path / "missing.yaml"),
    ]  # fmt: skip
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("hmpf-calibrate: error: cannot read config") and "Traceback" not in err


def test_a_bank_scored_with_other_settings_is_refused(route):
    """The bank holds ``hog`` and ``gist`` under the config's ids, but the config sets hog
    otherwise: its scores are not this config's, so the fit refuses (it fitted on them
    before), naming the method; the same settings under another name still fit."""
    _, train = route
    other = parse_config(
        {
            "name": "other-hog",
            "methods": {"hog": {"cell_size": 20}},
            "tiers": [{"methods": ["hog", "gist"], "k": 1}],
        }
    )
    with pytest.raises(ConfigError, match=r"bank's hog scored with other settings"):
        fit_config_acceptance(other, train, target_precision=0.9, model=False)
    same = parse_config({"name": "same", "tiers": [{"methods": ["hog", "gist"], "k": 1}]})
    fit = fit_config_acceptance(same, train, target_precision=0.9, model=False)
    assert fit.config.acceptance is not None
