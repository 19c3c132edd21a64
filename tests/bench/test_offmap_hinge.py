"""bench/offmap_hinge.py: its variants' recipes, the training figures (leave one route out,
foreign frames told from removed stretches by their query index) and the choice."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.confidence import expected_calibration_error, feature_matrix
from hmpf.evaluation.acceptance import Answers, RoutePart, _fit, _pooled

ROOT = Path(__file__).resolve().parents[2]
NAMES = ("quality", "ref_z", "ref_z_low", "map_prior")


def _load(name: str):
    path = ROOT / "bench" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def oh():
    return _load("offmap_hinge")


def _answers(z: np.ndarray, correct: np.ndarray, query: np.ndarray, prior: float) -> Answers:
    rng = np.random.default_rng(len(z))
    feats = [
        {
            "quality": float(rng.normal(1.0 if c else 0.0, 1.0)),
            "ref_z": float(v),
            "ref_z_low": min(float(v), 0.0),
            "map_prior": prior,
        }
        for v, c in zip(z, correct, strict=True)
    ]
    return Answers(feats, correct, np.zeros(len(z)), query)


def _part(name: str, seed: int, prior: float) -> tuple[RoutePart, int]:
    rng = np.random.default_rng(seed)
    nq = 120
    right = rng.random(nq) < 0.7
    inside = _answers(rng.normal(np.where(right, 2.0, 0.5), 1.0), right, np.arange(nq), prior)
    removed = rng.normal(0.0, 1.0, 40)  # the route's own places, taken out of the map
    foreign = rng.normal(-1.5, 0.7, 30)  # another data set: below unrelated places
    outside = _answers(
        np.concatenate([removed, foreign]),
        np.zeros(70, bool),
        np.concatenate([rng.integers(0, nq, 40), nq + np.arange(30)]),
        prior,
    )
    return RoutePart(name, inside, outside), nq


def test_training_figures_are_each_route_predicted_by_the_others(oh):
    built = [_part(n, s, p) for n, s, p in (("a", 1, 1.2), ("b", 2, 1.0), ("c", 3, -2.0))]
    parts, n_train = [b[0] for b in built], [b[1] for b in built]
    got = oh.training_figures(parts, n_train, NAMES, 0.1)
    assert list(got) == ["a", "b", "c"]
    for k, part in enumerate(parts):
        rest = [p for j, p in enumerate(parts) if j != k]
        X, y, w, _, _ = _pooled(rest, NAMES, 0.1)
        model = _fit(X, y, NAMES, w)  # ref_z_low staged, as the shipped fit does
        p_in = np.asarray(model.predict(feature_matrix(part.answers.features, NAMES)))
        p_out = np.asarray(model.predict(feature_matrix(part.outside.features, NAMES)))
        fig = got[part.name]
        assert fig["ece_in_map"] == pytest.approx(
            expected_calibration_error(p_in, part.answers.correct)
        )
        assert fig["foreign_n"] == 30 and fig["removed_n"] == 40
        assert fig["foreign_mean_p"] == pytest.approx(p_out[40:].mean())
        assert fig["removed_mean_p"] == pytest.approx(p_out[:40].mean())
        # frames far below unrelated places get less than the route's own removed places
        assert fig["foreign_mean_p"] < fig["removed_mean_p"]
        low_in = np.mean([f["ref_z"] < 0 for f in part.answers.features])
        low_away = np.mean([f["ref_z"] < 0 for f in part.outside.features[40:]])
        assert fig["in_map_hinged"] == fig["in_map_below_unrelated"] == pytest.approx(low_in)
        assert fig["foreign_hinged"] == fig["foreign_below_unrelated"] == pytest.approx(low_away)
        assert fig["in_map_hinged"] < 0.2 < 0.9 < fig["foreign_hinged"]


def test_variants_recipes_and_the_choice(oh):
    recipe = oh.Recipe
    base = recipe.of(True, 0.9)
    assert oh.with_hinges(base, ()) == base
    both = oh.with_hinges(base, ("ref_z_low", "cand_z_low"))
    assert both.single == (*base.single[:-1], "ref_z_low", "cand_z_low", "map_prior")
    assert oh.with_hinges(both, ("ref_z_low",)).single == (
        *base.single[:-1], "ref_z_low", "map_prior",
    )  # fmt: skip
    assert oh.with_hinges(recipe.of(False), ("cand_z_low",)).single[-1] == "cand_z_low"
    assert {k for _, k in oh.VARIANTS.values()} >= {None, 0.5}  # the shipped knot is tried
    ans = Answers([{"cand_z": 0.2}, {"cand_z": 1.7}], np.zeros(2, bool), np.zeros(2), np.arange(2))
    oh.set_knot(ans, 0.5)
    assert [f["cand_z_low"] for f in ans.features] == [pytest.approx(-0.3), 0.0]
    oh.set_knot(ans, None)  # left as it is
    assert ans.features[0]["cand_z_low"] == pytest.approx(-0.3)
    feats = [
        {"ref_z": 0.3, "ref_z_low": 0.0, "cand_z_low": -0.1},
        {"ref_z": -1.0, "ref_z_low": -1.0},
    ]
    assert oh.hinged(feats[:1], ("quality", "ref_z_low")) == 0.0
    assert oh.hinged(feats[:1], ("ref_z_low", "cand_z_low")) == 1.0  # cand_z below its knot
    assert oh.hinged(feats[1:], ("ref_z_low",)) == 1.0 and oh.hinged(feats, ("quality",)) == 0.0
    assert oh.below_unrelated(feats) == 0.5 and oh.below_unrelated([]) == 0.0
    train = {
        "none": {"a": {"foreign_mean_p": 0.4}, "b": {"foreign_mean_p": 0.1}},
        "one": {"a": {"foreign_mean_p": 0.2}, "b": {"foreign_mean_p": 0.25}},
        "two": {"a": {"foreign_mean_p": 0.05}, "b": {"foreign_mean_p": 0.3}},
    }
    assert oh.choose(train) == "one"  # the lowest worst route, not the lowest mean
