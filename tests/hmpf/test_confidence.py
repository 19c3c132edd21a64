"""hmpf.confidence: the evidence of an answer, the logistic model, thresholds, calibration."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import minimize

from hmpf.confidence import (
    FEATURES,
    FORMAT_VERSION,
    LOGIT_CLIP,
    SEQUENCE_FEATURES,
    ConfidenceModel,
    ModelError,
    answer_features,
    expected_calibration_error,
    feature_matrix,
    reliability,
    threshold_for_precision,
)
from hmpf.errors import HmpfError
from hmpf.hierarchy import HierarchyResult, TierResult
from hmpf.sequence import Estimate, RouteMap

NAN = float("nan")
#: Tier 1's mean score (both methods the same): the answer 3 scores 0.9, beaten by 4 and 5.
TIER1 = np.array([0.2, 0.1, 0.0, 0.9, 1.0, 0.95, 0.3, 0.4, 0.6, 0.5])


def make_result(
    *,
    match: int = 3,
    quality: float = 2.0,
    final: tuple[int, ...] = (3, 4, 8, 0),
    combined: tuple[float, ...] = (2.0, 1.5, 0.5, -1.0),
    tier1: np.ndarray = TIER1,
    final_scores: dict[str, np.ndarray] | None = None,
) -> HierarchyResult:
    """A two-tier result over 10 references on one route (file order)."""
    n = len(tier1)
    F = np.array(final, dtype=np.int64)
    if final_scores is None:
        c, d = np.full(n, NAN), np.full(n, NAN)
        c[F], d[F] = [0.9, 1.0, 0.2, 0.0], [0.5, 0.4, 1.0, 0.0]  # c: best 4, d: best 8
        final_scores = {"c": c, "d": d}
    t1 = TierResult(["a", "b"], None, {"a": tier1.copy(), "b": tier1.copy()}, F, 0.0)
    t2 = TierResult(list(final_scores), F, final_scores, F[:1], 0.0)
    return HierarchyResult(match, quality, F, np.array(combined, dtype=float), [t1, t2])


ROUTES = RouteMap.from_metadata(10)


# -- features -------------------------------------------------------------------------------------


def test_features_hand_checked() -> None:
    f = answer_features(make_result(), ROUTES, window=2)
    assert list(f) == list(FEATURES)
    assert f["quality"] == 2.0
    # 4 (z 1.5) is next door; the best rival outside +-2 is 8 (z 0.5).
    assert f["margin"] == pytest.approx(1.5)
    # c's best (4) is within 2 of 3, d's best (8) is not.
    assert f["agreement"] == 0.5
    # 4 and 5 score higher in tier 1.
    assert f["tier1_rank"] == pytest.approx(math.log1p(2))
    # Outside 1..5: the best is 8 (0.6).
    assert f["tier1_margin"] == pytest.approx(0.9 - 0.6)
    assert f["tier1_z"] == pytest.approx((0.9 - TIER1.mean()) / TIER1.std())
    assert f["n_final"] == pytest.approx(math.log1p(4))


def test_window_decides_what_is_a_rival() -> None:
    # window 0: 4 is a rival (margin 0.5) and c no longer agrees.
    f = answer_features(make_result(), ROUTES, window=0)
    assert f["margin"] == pytest.approx(0.5)
    assert f["agreement"] == 0.0
    assert f["tier1_margin"] == pytest.approx(0.9 - 1.0)
    # window 5: 8 (5 steps away) is next door, 0 too (3 steps): no rival left.
    f = answer_features(make_result(), ROUTES, window=5)
    assert f["margin"] == pytest.approx(2.0)  # no rival: the rival at z = 0
    assert f["agreement"] == 1.0


def test_nan_scores_give_finite_defaults() -> None:
    c = np.full(10, NAN)
    c[[3, 4, 8, 0]] = [1.0, 0.5, 0.2, 0.0]
    tier1 = TIER1.copy()
    tier1[3] = NAN  # the answer unscored in tier 1
    res = make_result(
        quality=NAN,
        combined=(NAN, NAN, NAN, NAN),
        tier1=tier1,
        final_scores={"c": c, "d": np.full(10, NAN)},
    )
    f = answer_features(res, ROUTES)
    assert all(math.isfinite(v) for v in f.values())
    assert f["quality"] == 0.0 and f["margin"] == 0.0
    assert f["agreement"] == 0.5  # d has no finite score: does not agree
    assert f["tier1_rank"] == pytest.approx(math.log1p(10))
    assert f["tier1_z"] == 0.0
    assert f["tier1_margin"] == pytest.approx(0.0 - 0.6)  # NaN reads as 0


def test_nan_rival_is_ignored() -> None:
    f = answer_features(make_result(combined=(2.0, 1.5, NAN, -1.0)), ROUTES)
    assert f["margin"] == pytest.approx(3.0)  # 8 is NaN: the rival is 0 (z -1)


def test_no_answer_and_estimates() -> None:
    empty = HierarchyResult(-1, NAN, np.zeros(0, np.int64), np.zeros(0), [])
    f = answer_features(empty, ROUTES, estimate=Estimate(-1, NAN, False, 0))
    assert f == {
        "quality": 0.0,
        "margin": 0.0,
        "agreement": 0.0,
        "tier1_rank": pytest.approx(math.log1p(10)),
        "tier1_margin": 0.0,
        "tier1_z": 0.0,
        "n_final": 0.0,
        "sequence_mass": 0.0,
        "sequence_logit": -LOGIT_CLIP,
        "sequence_agrees": 0.0,
    }
    f = answer_features(make_result(), ROUTES, estimate=Estimate(5, 0.8, False, 3))
    assert list(f) == list(FEATURES + SEQUENCE_FEATURES)
    assert f["sequence_mass"] == 0.8 and f["sequence_agrees"] == 1.0
    assert f["sequence_logit"] == pytest.approx(math.log(0.8 / 0.2))
    f = answer_features(make_result(), ROUTES, estimate=Estimate(6, NAN, False, 3))
    assert f["sequence_mass"] == 0.0 and f["sequence_agrees"] == 0.0
    f = answer_features(make_result(), ROUTES, estimate=Estimate(1, 1.0, True, 3))
    assert f["sequence_logit"] == LOGIT_CLIP and f["sequence_agrees"] == 1.0
    with pytest.raises(HmpfError):
        answer_features(make_result(), ROUTES, window=-1)
    with pytest.raises(HmpfError, match="route map has 12"):
        answer_features(make_result(), RouteMap.from_metadata(12))


def test_feature_matrix_orders_and_refuses_missing() -> None:
    rows = [{"a": 1.0, "b": 2.0}, {"b": 4.0, "a": 3.0}]
    assert feature_matrix(rows, ["b", "a"]).tolist() == [[2.0, 1.0], [4.0, 3.0]]
    assert feature_matrix([], ["a"]).shape == (0, 1)
    with pytest.raises(ModelError, match="c"):
        feature_matrix(rows, ["a", "c"])


# -- the logistic model -------------------------------------------------------------------------


def synthetic(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 3)) * [1.0, 2.0, 1.5] + [0.0, 1.0, -2.0]
    beta, b0 = np.array([1.5, -1.0, 2.0]), 0.3
    y = rng.random(n) < 1 / (1 + np.exp(-(X @ beta + b0)))
    return X, y, beta, b0


def raw_coefficients(m: ConfidenceModel) -> tuple[np.ndarray, float]:
    coef = np.array(m.coef) / np.array(m.scale)
    return coef, m.intercept - float(coef @ np.array(m.mean))


def test_fit_recovers_known_coefficients() -> None:
    X, y, beta, b0 = synthetic(20000)
    m = ConfidenceModel.fit(X, y, ["x1", "x2", "x3"], l2=1.0)
    coef, intercept = raw_coefficients(m)
    np.testing.assert_allclose(coef, beta, rtol=0.08)
    assert intercept == pytest.approx(b0, abs=0.1)
    again = ConfidenceModel.fit(X, y, ["x1", "x2", "x3"], l2=1.0)
    assert again == m  # deterministic, bit for bit


@pytest.mark.parametrize(
    ("l2", "weighted"), [(0.0, False), (1.0, False), (10.0, False), (1.0, True)]
)
def test_fit_is_the_maximum_of_the_regularised_likelihood(l2: float, weighted: bool) -> None:
    X, y, _, _ = synthetic(300, seed=1)
    sw = np.random.default_rng(2).uniform(0.2, 3.0, len(y)) if weighted else np.ones(len(y))
    m = ConfidenceModel.fit(X, y, ["x1", "x2", "x3"], l2=l2, sample_weight=sw if weighted else None)
    mean = np.average(X, axis=0, weights=sw)
    Z = np.hstack([np.ones((len(y), 1)), (X - mean) / np.sqrt(np.average((X - mean) ** 2, 0, sw))])
    t = y.astype(float)

    def objective(w: np.ndarray) -> tuple[float, np.ndarray]:
        s = Z @ w
        loss = np.sum(sw * (np.logaddexp(0, s) - t * s)) + l2 / 2 * np.sum(w[1:] ** 2)
        grad = Z.T @ (sw * (1 / (1 + np.exp(-s)) - t)) + l2 * np.r_[0.0, w[1:]]
        return float(loss), grad

    best = minimize(objective, np.zeros(4), jac=True, method="BFGS", options={"gtol": 1e-10})
    np.testing.assert_allclose([m.intercept, *m.coef], best.x, atol=1e-6)


def test_offsets_enter_the_log_odds_unfitted() -> None:
    """An offset feature (a known prior log-odds) is added as it is: the other coefficients
    are the maximum of the likelihood with it in the linear predictor (scipy's optimiser on
    the same objective), and the stored model predicts with it at coefficient 1."""
    X, y, _, _ = synthetic(400, seed=3)
    prior = np.where(np.arange(len(y)) % 2 == 0, 1.5, -2.0)  # two "maps"
    Xo = np.column_stack([X, prior])
    names = ["x1", "x2", "x3", "map_prior"]
    m = ConfidenceModel.fit(Xo, y, names, l2=1.0, offsets=["map_prior"])
    assert (m.mean[3], m.scale[3], m.coef[3]) == (0.0, 1.0, 1.0)
    mean = X.mean(0)
    Z = np.hstack([np.ones((len(y), 1)), (X - mean) / X.std(0)])
    t = y.astype(float)

    def objective(w: np.ndarray) -> tuple[float, np.ndarray]:
        s = Z @ w + prior
        loss = np.sum(np.logaddexp(0, s) - t * s) + 0.5 * np.sum(w[1:] ** 2)
        grad = Z.T @ (1 / (1 + np.exp(-s)) - t) + np.r_[0.0, w[1:]]
        return float(loss), grad

    best = minimize(objective, np.zeros(4), jac=True, method="BFGS", options={"gtol": 1e-10})
    np.testing.assert_allclose([m.intercept, *m.coef[:3]], best.x, atol=1e-6)
    want = 1 / (1 + np.exp(-(Z @ best.x + prior)))
    np.testing.assert_allclose(m.predict(Xo), want, atol=1e-6)
    # the prior moves the probability by exactly its log-odds
    lifted = Xo.copy()
    lifted[:, 3] += 1.0
    np.testing.assert_allclose(m.logit(lifted), m.logit(Xo) + 1.0, atol=1e-12)
    with pytest.raises(HmpfError, match="not features"):
        ConfidenceModel.fit(X, y, names[:3], offsets=["map_prior"])


def test_a_staged_fit_is_the_first_stage_plus_the_likelihoods_maximum_in_the_rest() -> None:
    """fit_staged: the first stage is exactly :meth:`fit` over the other features (with the
    offsets); the staged coefficients (raw, no intercept) maximise the weighted, penalised
    likelihood with the first stage's log-odds fixed (scipy's optimiser on that objective);
    where the staged features are 0 the model predicts what the first stage does."""
    X, y, _, _ = synthetic(500, seed=5)
    rng = np.random.default_rng(6)
    prior = np.where(np.arange(len(y)) % 3 == 0, 1.2, -0.7)
    # two hinges, 0 on most rows, low where the label is mostly wrong
    h1 = np.minimum(X[:, 0] + rng.normal(0, 0.5, len(y)), 0.0) * (rng.random(len(y)) < 0.3)
    h2 = np.minimum(h1 * 0.5 + rng.normal(0, 0.3, len(y)), 0.0)
    names = ["quality", "agreement", "ref_z_low", "map_prior", "cand_z_low"]
    Xs = np.column_stack([X[:, 0], X[:, 1], h1, prior, h2])
    sw = rng.uniform(0.5, 2.0, len(y))
    m = ConfidenceModel.fit_staged(
        Xs, y, names, ["ref_z_low", "cand_z_low"], l2=1.0, sample_weight=sw, offsets=["map_prior"]
    )
    assert m.features == tuple(names)
    first = ConfidenceModel.fit(
        Xs[:, [0, 1, 3]], y, ["quality", "agreement", "map_prior"], sample_weight=sw,
        offsets=["map_prior"],
    )  # fmt: skip
    assert m.intercept == first.intercept
    for name, mean, scale, coef in zip(
        first.features, first.mean, first.scale, first.coef, strict=True
    ):
        i = names.index(name)
        assert (m.mean[i], m.scale[i], m.coef[i]) == (mean, scale, coef)
    off = first.logit(Xs[:, [0, 1, 3]])
    H = Xs[:, [2, 4]]
    t = y.astype(float)

    def objective(b: np.ndarray) -> tuple[float, np.ndarray]:
        s = off + H @ b
        loss = np.sum(sw * (np.logaddexp(0, s) - t * s)) + 0.5 * np.sum(b**2)
        grad = H.T @ (sw * (1 / (1 + np.exp(-s)) - t)) + b
        return float(loss), grad

    best = minimize(objective, np.zeros(2), jac=True, method="BFGS", options={"gtol": 1e-10})
    assert (m.mean[2], m.scale[2], m.mean[4], m.scale[4]) == (0.0, 1.0, 0.0, 1.0)
    np.testing.assert_allclose([m.coef[2], m.coef[4]], best.x, atol=1e-6)
    assert m.coef[2] > 0 or m.coef[4] > 0  # a hinge that is low where answers are wrong
    zero = (h1 == 0) & (h2 == 0)
    assert zero.any() and not zero.all()
    np.testing.assert_allclose(m.logit(Xs)[zero], off[zero], rtol=1e-13, atol=1e-13)
    # one ordinary model: stored as version 1 and read back the same
    d = m.to_dict()
    assert d["version"] == 1 and "gate" not in d
    np.testing.assert_array_equal(ConfidenceModel.from_dict(d).predict(Xs), m.predict(Xs))
    # nothing staged: fit itself
    assert ConfidenceModel.fit_staged(X, y, ["x1", "x2", "x3"], []) == ConfidenceModel.fit(
        X, y, ["x1", "x2", "x3"]
    )
    with pytest.raises(ModelError, match="not features"):
        ConfidenceModel.fit_staged(X, y, ["x1", "x2", "x3"], ["x4"])
    with pytest.raises(ModelError, match="first stage"):
        ConfidenceModel.fit_staged(X, y, ["x1", "x2", "x3"], ["x1", "x2", "x3"])
    with pytest.raises(ModelError, match="shape"):
        ConfidenceModel.fit_staged(X[:, :2], y, ["x1", "x2", "x3"], ["x3"])
    with pytest.raises(ModelError, match="duplicate"):
        ConfidenceModel.fit_staged(X, y, ["x1", "x2", "x3"], ["x3", "x3"])
    with pytest.raises(ModelError, match="duplicate"):
        ConfidenceModel.fit_staged(X, y, ["x1", "x3", "x3"], ["x3"])
    with pytest.raises(ModelError, match="both staged and offsets"):
        ConfidenceModel.fit_staged(X, y, ["x1", "x2", "x3"], ["x3"], offsets=["x3"])


def test_terms_added_to_a_model_are_raw_log_odds_and_nothing_else_moves() -> None:
    """with_terms: each term adds coefficient x value to the log-odds (mean 0, scale 1),
    the rest of the model as it was; refused for a gated model, a name already there, or a
    coefficient that is not finite."""
    X, y, _, _ = synthetic(300, seed=8)
    m = ConfidenceModel.fit(X, y, ["x1", "x2", "x3"])
    w = m.with_terms({"ref_z_low": 0.4, "cand_z_low": 1.5})
    assert w.features == ("x1", "x2", "x3", "ref_z_low", "cand_z_low")
    assert (w.mean[:3], w.scale[:3], w.coef[:3], w.intercept) == (
        m.mean,
        m.scale,
        m.coef,
        m.intercept,
    )
    rng = np.random.default_rng(9)
    H = np.minimum(rng.normal(0, 1, (len(y), 2)), 0.0)
    np.testing.assert_allclose(
        w.logit(np.hstack([X, H])), m.logit(X) + 0.4 * H[:, 0] + 1.5 * H[:, 1], atol=1e-12
    )
    assert m.with_terms({}) == m
    with pytest.raises(ModelError, match="already has"):
        m.with_terms({"x2": 1.0})
    with pytest.raises(ModelError, match="non-finite"):
        m.with_terms({"h": float("nan")})
    inside = np.arange(len(y)) % 4 != 0
    gated = ConfidenceModel.fit_gated(X, y, ["x1", "x2", "x3"], inside)
    with pytest.raises(ModelError, match="gated"):
        gated.with_terms({"h": 1.0})


def test_separable_data_gives_finite_coefficients() -> None:
    X = np.array([[0.0], [1.0], [2.0], [3.0]])
    m = ConfidenceModel.fit(X, np.array([0, 0, 1, 1]), ["quality"], l2=1.0)
    assert all(math.isfinite(v) for v in (*m.coef, m.intercept))
    assert m.predict(np.array([[3.0]]))[0] > 0.5 > m.predict(np.array([[0.0]]))[0]


def test_fit_refuses_bad_input() -> None:
    X, y = np.zeros((4, 2)), np.array([0, 1, 0, 1])
    for args in (
        (X, y[:3], ["a", "b"]),  # shapes
        (X, y, ["a"]),  # names
        (X, y, ["a", "a"]),  # duplicates
        (np.where(np.eye(4, 2) > 0, np.nan, 0.0), y, ["a", "b"]),  # NaN
        (X, np.array([0, 1, 2, 1]), ["a", "b"]),  # labels
        (X[:1], y[:1], ["a", "b"]),  # too few
    ):
        with pytest.raises(ModelError):
            ConfidenceModel.fit(*args)
    with pytest.raises(ModelError):
        ConfidenceModel.fit(X, y, ["a", "b"], l2=-1.0)
    for sw in (np.ones(3), np.array([1.0, -1.0, 1.0, 1.0]), np.zeros(4), np.full(4, np.nan)):
        with pytest.raises(ModelError, match="sample_weight"):
            ConfidenceModel.fit(X, y, ["a", "b"], sample_weight=sw)


def test_weights_count_like_repeated_answers() -> None:
    X, y, _, _ = synthetic(200, seed=4)
    twice = ConfidenceModel.fit(np.vstack([X, X[:50]]), np.r_[y, y[:50]], ["a", "b", "c"])
    weighted = ConfidenceModel.fit(
        X, y, ["a", "b", "c"], sample_weight=np.r_[np.full(50, 2.0), np.ones(150)]
    )
    np.testing.assert_allclose(weighted.coef, twice.coef, atol=1e-9)
    np.testing.assert_allclose(weighted.mean, twice.mean, atol=1e-12)


def fitted() -> ConfidenceModel:
    rng = np.random.default_rng(3)
    X = rng.normal(size=(200, 3))
    y = rng.random(200) < 1 / (1 + np.exp(-3 * X[:, 0]))
    return ConfidenceModel.fit(X, y, ["quality", "margin", "agreement"])


def test_predict_is_a_probability() -> None:
    m = fitted()
    X = np.array([[1e6, 0.0, 0.0], [-1e6, 0.0, 0.0], [0.0, 0.0, 0.0]])
    p = m.predict(X)
    assert isinstance(p, np.ndarray) and p.shape == (3,)
    assert np.all((p > 0) & (p < 1)) and p[0] > 0.99 and p[1] < 0.01
    one = m.predict({"quality": 0.5, "margin": 0.1, "agreement": 1.0, "other": 7.0})
    assert isinstance(one, float)
    assert one == pytest.approx(float(m.predict(np.array([[0.5, 0.1, 1.0]]))[0]))
    with pytest.raises(ModelError, match="margin"):
        m.predict({"quality": 0.5, "agreement": 1.0})
    with pytest.raises(ModelError, match="non-finite"):
        m.predict(np.array([[NAN, 0.0, 0.0]]))
    with pytest.raises(ModelError):
        m.predict(np.zeros((2, 4)))


def test_round_trip_through_json() -> None:
    m = fitted()
    data = json.loads(json.dumps(m.to_dict()))
    # without a gate a model is written as version 1, which every hmpf reads
    assert data["version"] == 1 and data["features"] == list(m.features)
    back = ConfidenceModel.from_dict(data, expected=["agreement", "margin", "quality"])
    assert back == m
    X = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_array_equal(back.predict(X), m.predict(X))


def _broken(**changes: object) -> dict[str, object]:
    data = fitted().to_dict()
    for k, v in changes.items():
        if v is KeyError:
            del data[k]
        else:
            data[k] = v
    return data


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (_broken(version=3), "version 3"),
        (_broken(version=True), "version True"),
        (_broken(gate=fitted().to_dict()), "version 1 confidence model has no gate"),
        (_broken(version=KeyError), "version None"),
        (_broken(format="something else"), "not a confidence model"),
        (_broken(coef=KeyError), "lacks coef"),
        (_broken(features=["quality", "margin", "speed"]), "unknown features.*speed"),
        (_broken(features=["quality", "margin", "margin"]), "distinct"),
        (_broken(features="quality"), "list of names"),
        (_broken(mean=[0.0, 0.0]), "'mean' must hold 3"),
        (_broken(coef=[1.0, NAN, 0.0]), "non-finite"),
        (_broken(scale=[1.0, math.inf, 1.0]), "non-finite"),
        (_broken(scale=[1.0, 0.0, 1.0]), "positive"),
        (_broken(intercept="0.5"), "non-number"),
        (_broken(intercept=True), "non-number"),
        (_broken(l2=NAN), "non-finite"),
    ],
)
def test_from_dict_refuses(data: dict[str, object], message: str) -> None:
    with pytest.raises(ModelError, match=message):
        ConfidenceModel.from_dict(data)


def test_from_dict_refuses_other_features_than_expected() -> None:
    data = fitted().to_dict()
    with pytest.raises(ModelError, match=r"missing \['tier1_rank'\]"):
        ConfidenceModel.from_dict(data, expected=["quality", "margin", "agreement", "tier1_rank"])
    with pytest.raises(ModelError, match=r"extra \['agreement'\]"):
        ConfidenceModel.from_dict(data, expected=["quality", "margin"])
    with pytest.raises(ModelError):
        ConfidenceModel.from_dict(["not", "a", "mapping"])  # type: ignore[arg-type]
    assert issubclass(ModelError, HmpfError)


# -- thresholds and calibration -----------------------------------------------------------------


def test_threshold_for_precision_hand_computed() -> None:
    p = np.array([0.9, 0.8, 0.7, 0.6, 0.5])
    c = np.array([1, 1, 0, 1, 1], dtype=bool)
    assert threshold_for_precision(p, c, 0.99) == 0.8
    assert threshold_for_precision(p, c, 0.85) == 0.8  # 0.6 gives 3/4, 0.7 gives 2/3
    assert threshold_for_precision(p, c, 0.8) == 0.5  # 4/5
    assert threshold_for_precision(p[::-1], c[::-1], 0.8) == 0.5  # order does not matter
    # Ties are accepted together: 0.8 would bring in a wrong answer with it.
    assert threshold_for_precision(np.array([0.9, 0.8, 0.8]), np.array([1, 1, 0]), 0.99) == 0.9
    # Unreachable, or nothing to accept: 1.0.
    assert threshold_for_precision(np.array([0.9, 0.8]), np.array([0, 1]), 0.99) == 1.0
    assert threshold_for_precision(np.zeros(0), np.zeros(0, bool), 0.99) == 1.0
    with pytest.raises(HmpfError):
        threshold_for_precision(p, c[:3])


def test_ece_and_reliability_hand_computed() -> None:
    p = np.array([0.1, 0.15, 0.9, 0.95, 1.0])
    c = np.array([0, 1, 1, 1, 1])
    rel = reliability(p, c, bins=10)
    assert rel.count.tolist() == [0, 2, 0, 0, 0, 0, 0, 0, 0, 3]  # 1.0 in the last bin
    assert rel.predicted[1] == pytest.approx(0.125) and rel.observed[1] == 0.5
    assert rel.predicted[9] == pytest.approx(0.95) and rel.observed[9] == 1.0
    assert np.isnan(rel.predicted[0]) and np.isnan(rel.observed[0])
    assert rel.lower[1] == pytest.approx(0.1) and rel.upper[9] == 1.0
    # 2/5 * |0.125 - 0.5| + 3/5 * |0.95 - 1|
    assert expected_calibration_error(p, c) == pytest.approx(0.4 * 0.375 + 0.6 * 0.05)
    assert expected_calibration_error(np.array([0.3, 0.3]), np.array([0, 1]), bins=1) == (
        pytest.approx(0.2)
    )
    assert expected_calibration_error(np.zeros(0), np.zeros(0)) == 0.0
    for bad in (np.array([1.2]), np.array([NAN])):
        with pytest.raises(HmpfError):
            reliability(bad, np.array([1]))
    with pytest.raises(HmpfError):
        reliability(p, c, bins=0)


def test_threshold_floor_and_outside_floor() -> None:
    from hmpf.evaluation.acceptance import outside_floor

    p = np.array([0.9, 0.8, 0.7, 0.6, 0.5])
    c = np.array([1, 1, 0, 1, 1], dtype=bool)
    assert threshold_for_precision(p, c, 0.75) == 0.5  # 4/5
    assert threshold_for_precision(p, c, 0.75, floor=0.55) == 0.6  # 3/4; 0.5 is below
    assert threshold_for_precision(p, c, 0.75, floor=0.85) == 0.9
    assert threshold_for_precision(p, c, 0.75, floor=0.95) == 1.0
    # Out-of-map answers: at most max_rate of them may reach the threshold.
    out = np.array([0.2, 0.95, 0.5, 0.7])
    assert outside_floor(out, 0.0) > 0.95 and outside_floor(out, 0.0) == np.nextafter(0.95, 1)
    assert np.mean(out >= outside_floor(out, 0.25)) == 0.25  # one of four
    assert outside_floor(out, 1.0) == 0.0 and outside_floor(np.zeros(0), 0.01) == 0.0


# -- absolute evidence: the references' profile --------------------------------------------------


class _Dot:
    """A global method whose raw score is the dot product (higher is better)."""

    higher_is_better = True

    def pairwise(self, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.asarray(q, np.float64) @ np.asarray(r, np.float64).T


class _Dist(_Dot):
    higher_is_better = False

    def pairwise(self, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.linalg.norm(q[:, None, :] - r[None, :, :], axis=2)


def _globals():
    from hmpf.methods.base import GlobalMethod

    # Register the fakes as global methods without building real ones.
    dot = type("Dot", (_Dot, GlobalMethod), {"_extract": None, "name": "dot"})
    dist = type("Dist", (_Dist, GlobalMethod), {"_extract": None, "name": "dist"})
    for cls in (dot, dist):
        cls.__abstractmethods__ = frozenset()
    return dot(), dist()


def test_profile_equals_brute_force_every_chunk_and_sample_size() -> None:
    from hmpf.confidence import ReferenceProfile

    rng = np.random.default_rng(3)
    n, d = 23, 5
    db = {"dot": rng.normal(size=(n, d)), "dist": rng.normal(size=(n, d))}
    dot, dist = _globals()
    methods = {"dot": dot, "dist": dist, "local": object()}
    routes = RouteMap.from_metadata(n, sequence=np.array(["a"] * 12 + ["b"] * 11))
    for sample, chunk, window in ((64, 5, 2), (7, 4, 1), (7, 100, 0)):
        prof = ReferenceProfile.build(
            methods, db, ["dot", "local", "dist"], routes, sample=sample, chunk=chunk, window=window
        )
        assert prof.methods == ("dot", "dist") and prof.sign == (1.0, -1.0)
        pick = (
            np.arange(n)
            if n <= sample
            else np.sort(np.random.default_rng(0).choice(n, sample, replace=False))
        )
        for i, (mid, m) in enumerate((("dot", dot), ("dist", dist))):
            for r in range(n):
                vals = [
                    float(m.pairwise(db[mid][s][None], db[mid][r][None])[0, 0])
                    for s in pick
                    if routes.separation(int(s), r) > window
                ]
                assert prof.mean[i, r] == pytest.approx(np.mean(vals), rel=1e-12)
                assert prof.std[i, r] == pytest.approx(np.std(vals), rel=1e-9, abs=1e-12)
    with pytest.raises(HmpfError, match="no stored descriptors"):
        ReferenceProfile.build(methods, {"dot": db["dot"]}, ["dot", "dist"], routes)
    with pytest.raises(HmpfError, match="holds 3 references"):
        ReferenceProfile.build(methods, {"dot": db["dot"][:3]}, ["dot"], routes)
    sub = prof.subset(np.array([4, 2]))
    assert np.array_equal(sub.mean, prof.mean[:, [4, 2]]) and sub.n == 2


def test_profile_z_is_the_lowest_signed_z_and_skips_what_is_missing() -> None:
    from hmpf.confidence import ReferenceProfile

    prof = ReferenceProfile(
        ("dot", "dist"),
        (1.0, -1.0),
        np.array([[0.0, 1.0], [5.0, 5.0]]),
        np.array([[1.0, 2.0], [2.0, 0.0]]),
    )
    # ref 0: dot (3 - 0)/1 = 3, dist -(1 - 5)/2 = 2 -> the lowest, 2.
    assert prof.z({"dot": np.array([3.0, 0.0]), "dist": np.array([1.0, 0.0])}, 0) == 2.0
    # ref 1: dist has no spread there, dot (0 - 1)/2.
    assert prof.z({"dot": np.array([3.0, 0.0]), "dist": np.array([1.0, 0.0])}, 1) == -0.5
    assert prof.z({"dot": np.array([NAN, 0.0])}, 0) != prof.z({"dot": np.array([NAN, 0.0])}, 0)
    assert math.isnan(prof.z({}, 0)) and math.isnan(prof.z({"dot": np.zeros(2)}, 5))


def test_profile_z_many_is_z_at_each_reference() -> None:
    from hmpf.confidence import ReferenceProfile
    from hmpf.fusion import Spread

    rng = np.random.default_rng(3)
    n = 12
    prof = ReferenceProfile(
        ("dot", "dist", "gone"),
        (1.0, -1.0, 1.0),
        rng.normal(size=(3, n)),
        np.abs(rng.normal(size=(3, n))) * np.where(rng.random((3, n)) < 0.2, 0.0, 1.0),
    )
    raw = {"dot": rng.normal(size=n), "dist": rng.normal(size=n)}
    raw["dot"][[2, 5]] = NAN
    raw["dist"][[5, 7]] = NAN
    refs = np.array([0, 2, 5, 7, 11, -1, n, 3])

    def brute(scores: dict[str, np.ndarray], known: set[int] | None = None) -> np.ndarray:
        out = []
        for r in refs:
            vals = []
            for i, m in enumerate(prof.methods):
                if m not in scores or not 0 <= r < n or (known is not None and r not in known):
                    continue
                x, mu, sd = scores[m][r], prof.mean[i, r], prof.std[i, r]
                if np.isfinite(x) and sd > 0:
                    vals.append(prof.sign[i] * (x - mu) / sd)
            out.append(min(vals) if vals else NAN)
        return np.array(out)

    got = prof.z_many(raw, refs)
    want = brute(raw)
    assert prof.z(raw, 0) == pytest.approx(want[0])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)])
    assert np.isnan(got[[2, 5, 6]]).all()  # both scores missing; outside the map
    # The same from a tier's entries (an approximate tier 1): only the entries are known.
    index = np.array([0, 3, 7, 11])
    spread = Spread(n, index, {m: raw[m][index] for m in raw})
    got_s = prof.z_many(spread, refs)
    want_s = brute(raw, set(index.tolist()))
    np.testing.assert_array_equal(np.isnan(got_s), np.isnan(want_s))
    np.testing.assert_allclose(got_s[~np.isnan(got_s)], want_s[~np.isnan(want_s)])
    assert np.isnan(got_s[1])  # reference 2 is not an entry


def test_features_with_a_profile_read_the_raw_tier1_scores() -> None:
    from hmpf.confidence import CAND_Z_KNOT, PROFILE_FEATURES, ReferenceProfile

    res = make_result()
    raw = np.linspace(0.0, 0.9, 10)
    res.tiers[0].raw = {"a": raw, "b": raw.copy()}
    prof = ReferenceProfile(("a",), (1.0,), np.full((1, 10), 0.1), np.full((1, 10), 0.2))
    plain = answer_features(res, ROUTES)
    assert not set(PROFILE_FEATURES) & set(plain)
    f = answer_features(res, ROUTES, profile=prof)
    assert f["ref_z"] == pytest.approx((raw[3] - 0.1) / 0.2)
    assert f["ref_z_low"] == 0.0  # above what unrelated frames score: the hinge is flat
    # cand_z: the best of the final candidates (3, 4, 8, 0): reference 8.
    assert f["cand_z"] == pytest.approx((raw[8] - 0.1) / 0.2) and f["cand_z_low"] == 0.0
    assert CAND_Z_KNOT == 0.5
    profiled = ("ref_z", "ref_z_low", "cand_z", "cand_z_low")
    assert {k: v for k, v in f.items() if k not in profiled} == plain
    low = ReferenceProfile(("a",), (1.0,), np.full((1, 10), 0.5), np.full((1, 10), 0.2))
    f_low = answer_features(res, ROUTES, profile=low)
    assert f_low["ref_z_low"] == f_low["ref_z"] == pytest.approx((raw[3] - 0.5) / 0.2)
    assert f_low["cand_z"] == pytest.approx((raw[8] - 0.5) / 0.2) and f_low["cand_z_low"] == 0.0
    # Every candidate below what unrelated frames score (a frame from elsewhere).
    off = ReferenceProfile(("a",), (1.0,), np.full((1, 10), 0.9), np.full((1, 10), 0.2))
    f_off = answer_features(res, ROUTES, profile=off)
    assert f_off["cand_z"] == pytest.approx((raw[8] - 0.9) / 0.2)
    assert f_off["cand_z_low"] == pytest.approx(f_off["cand_z"] - CAND_Z_KNOT)
    assert f_off["ref_z"] < f_off["cand_z"] < 0
    # Just above what unrelated frames score, below the knot: the hinge is not yet flat.
    near = ReferenceProfile(("a",), (1.0,), np.full((1, 10), 0.75), np.full((1, 10), 0.2))
    f_near = answer_features(res, ROUTES, profile=near)
    assert 0 < f_near["cand_z"] < CAND_Z_KNOT
    assert f_near["cand_z_low"] == pytest.approx(f_near["cand_z"] - CAND_Z_KNOT)
    est = Estimate(ref=7, mass=0.9, locked=True, speed=1.0, frames=3)
    g = answer_features(res, ROUTES, estimate=est, profile=prof)
    assert g["sequence_ref_z"] == pytest.approx((raw[7] - 0.1) / 0.2)
    # A result without raw scores, or an unscored reference: an unrelated one's score (0).
    res.tiers[0].raw = {}
    bare = answer_features(res, ROUTES, estimate=est, profile=prof)
    assert bare["sequence_ref_z"] == 0.0
    # ... and no z-score at any candidate: no evidence, both cand_z and its hinge 0
    assert bare["cand_z"] == bare["cand_z_low"] == 0.0
    # A model over the absolute evidence cannot be applied without the profile.
    m = ConfidenceModel(("ref_z",), (0.0,), (1.0,), (1.0,), 0.0)
    with pytest.raises(ModelError, match="ref_z"):
        m.predict(plain)
    with pytest.raises(ModelError, match="ref_z"):
        feature_matrix([plain], m.features)


def test_cand_z_reads_the_best_final_candidates_and_an_approximate_tier1() -> None:
    """cand_z: the highest z over the answer and at most CAND_Z_TOP final candidates, the
    best by Combined z (a single-tier config's candidates are the whole map); read from an
    approximate tier 1's entries as from whole arrays; no answer: no evidence."""
    from hmpf.confidence import CAND_Z_KNOT, CAND_Z_TOP, ReferenceProfile
    from hmpf.fusion import Spread

    n = 60
    routes = RouteMap.from_metadata(n)
    raw = np.linspace(0.0, 0.59, n)
    prof = ReferenceProfile(("a",), (1.0,), np.full((1, n), 0.5), np.full((1, n), 0.1))
    F = np.arange(n, dtype=np.int64)
    combined = -np.arange(n, dtype=float)  # reference 0 best, the last ones worst
    t1 = TierResult(["a"], None, {"a": raw.copy()}, F, 0.0, {"a": raw.copy()})
    res = HierarchyResult(0, 2.0, F, combined, [t1])
    f = answer_features(res, routes, profile=prof)
    # Only the CAND_Z_TOP best by Combined z (references 0..19) count: raw rises with the id.
    top = CAND_Z_TOP - 1
    assert f["cand_z"] == pytest.approx((raw[top] - 0.5) / 0.1)
    assert f["cand_z_low"] == pytest.approx(min(f["cand_z"] - CAND_Z_KNOT, 0.0))
    assert f["cand_z"] < 0 and f["ref_z"] == pytest.approx((raw[0] - 0.5) / 0.1)
    # The same scores as an approximate tier 1's entries (a few references scored).
    index = np.array([0, 3, top, 40])
    t1.raw = Spread(n, index, {"a": raw[index]})
    g = answer_features(res, routes, profile=prof)
    assert g["cand_z"] == pytest.approx(f["cand_z"]) and g["ref_z"] == f["ref_z"]
    t1.raw = Spread(n, np.array([0, 3, 40]), {"a": raw[[0, 3, 40]]})  # the top not scored
    assert answer_features(res, routes, profile=prof)["cand_z"] == pytest.approx(
        (raw[3] - 0.5) / 0.1
    )
    # No answer: every feature at its no-evidence value.
    none = HierarchyResult(-1, float("nan"), np.zeros(0, np.int64), np.zeros(0), [t1])
    h = answer_features(none, routes, profile=prof)
    assert h["cand_z"] == h["cand_z_low"] == h["ref_z"] == 0.0


def test_a_profile_that_knows_its_maps_prior_gives_every_answer_map_prior() -> None:
    from dataclasses import replace

    from hmpf.acceptance import Policy
    from hmpf.confidence import ALL_FEATURES, MAP_FEATURES, ModelError, ReferenceProfile

    res = make_result()
    res.tiers[0].raw = {"a": np.linspace(0.0, 0.9, 10)}
    prof = ReferenceProfile(("a",), (1.0,), np.full((1, 10), 0.1), np.full((1, 10), 0.2))
    without = answer_features(res, ROUTES, profile=prof)
    assert "map_prior" not in without
    known = replace(prof, map_prior=-1.25)
    est = Estimate(ref=7, mass=0.9, locked=True, speed=1.0, frames=3)
    for f, plain in (
        (answer_features(res, ROUTES, profile=known), without),
        (answer_features(res, ROUTES, estimate=est, profile=known),
         answer_features(res, ROUTES, estimate=est, profile=prof)),
    ):  # fmt: skip
        assert f.pop("map_prior") == -1.25 and f == plain
    assert known.subset(np.array([1, 3])).map_prior == -1.25
    # a model may read it; a policy with such a model refuses a profile without it
    assert set(MAP_FEATURES) <= set(ALL_FEATURES)
    names = ("quality", "map_prior")
    x = np.array([[0.0, 1.0], [1.0, -1.0], [2.0, 0.5], [3.0, 0.0]])
    model = ConfidenceModel.fit(x, [False, False, True, True], names)
    assert ConfidenceModel.from_dict(model.to_dict()) == model
    policy = Policy(2.0, model, 0.5)
    assert policy.needs_profile and policy.needs_map_prior
    assert policy.with_map_prior(known) is known
    for missing in (prof, None):
        with pytest.raises(ModelError, match="--map-prior"):
            policy.with_map_prior(missing)
    assert not Policy(2.0).needs_map_prior
    assert Policy(2.0).with_map_prior(None) is None  # no model reads it: nothing to refuse
    assert Policy(2.0).with_map_prior(prof) is prof
    # with a fallback, a profile without the prior gets it (one with its own keeps its own)
    safe = replace(policy, map_prior_fallback=-2.5)
    assert safe.with_map_prior(prof) == replace(prof, map_prior=-2.5)
    assert safe.with_map_prior(known) is known
    with pytest.raises(ModelError, match="--map-prior"):
        safe.with_map_prior(None)
    assert safe.describe()["map_prior_fallback"] == -2.5
    assert Policy(2.0, map_prior_fallback=-2.5).describe()["map_prior_fallback"] is None


# -- the gated model: P(in map) x P(right | in map) ---------------------------------------------


def gated_data(n: int = 600, seed: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows over (quality, ref_z, map_prior): in-map rows (ref_z high) right by quality,
    off-map rows (ref_z low) all wrong, whatever their quality."""
    rng = np.random.default_rng(seed)
    inside = rng.random(n) < 0.8
    quality = rng.normal(size=n)
    ref_z = np.where(inside, 2.0, -1.0) + rng.normal(size=n)
    prior = np.where(np.arange(n) % 2 == 0, 1.2, -2.3)
    right = inside & (rng.random(n) < 1 / (1 + np.exp(-(2 * quality + prior))))
    return np.column_stack([quality, ref_z, prior]), right, inside


GATED = ["quality", "ref_z", "map_prior"]


def test_a_gated_model_is_its_two_fits_multiplied() -> None:
    X, y, inside = gated_data()
    w = np.where(inside, 1.0, 0.5)
    m = ConfidenceModel.fit_gated(
        X, y, GATED, inside, l2=0.5, sample_weight=w, offsets=["map_prior"]
    )
    # the gate: every row, labelled in map or not, over the features that are not offsets
    gate = ConfidenceModel.fit(X[:, :2], inside, GATED[:2], l2=0.5, sample_weight=w)
    # the model: the in-map rows alone, with the offset
    main = ConfidenceModel.fit(
        X[inside], y[inside], GATED, l2=0.5, sample_weight=w[inside], offsets=["map_prior"]
    )
    assert m.gate is not None and m.gate.features == gate.features == ("quality", "ref_z")
    for got, ref in ((m.gate, gate), (m, main)):
        assert got.features == ref.features
        for key in ("mean", "scale", "coef", "intercept"):
            np.testing.assert_allclose(getattr(got, key), getattr(ref, key), rtol=1e-9)
    want = gate.predict(X[:, :2]) * main.predict(X)
    np.testing.assert_allclose(m.predict(X), want, rtol=1e-12)
    one = dict(zip(GATED, X[0], strict=True))
    assert m.predict(one) == pytest.approx(float(want[0]), rel=1e-12)
    # off-map rows now get a low probability from the gate
    assert float(np.mean(m.predict(X[~inside]))) < 0.5 * float(np.mean(main.predict(X[~inside])))


def test_the_product_s_log_odds_stay_finite_and_exact() -> None:
    from hmpf.confidence import _and_logit  # the helper under test

    a = np.array([-800.0, -30.0, -2.0, 0.0, 1.5, 30.0, 800.0, 40.0])
    b = np.array([3.0, 0.5, -1.0, 0.0, 2.5, 35.0, 800.0, -800.0])
    t = _and_logit(a, b)
    assert np.isfinite(t).all()
    # where floats hold both probabilities, the log-odds are those of their product
    mid = slice(1, 5)
    p = 1 / (1 + np.exp(-a[mid])) / (1 + np.exp(-b[mid]))
    np.testing.assert_allclose(t[mid], np.log(p / (1 - p)), rtol=1e-9)
    # both near certain: log-odds of 1 - (e^-30 + e^-35) approx, not inf
    assert t[5] == pytest.approx(-math.log(math.exp(-30) + math.exp(-35)), rel=1e-6)
    assert t[6] > 500 and t[7] < -700 and t[0] < -700


def test_a_gated_model_round_trips_as_version_2() -> None:
    X, y, inside = gated_data()
    m = ConfidenceModel.fit_gated(X, y, GATED, inside, offsets=["map_prior"])
    data = json.loads(json.dumps(m.to_dict()))
    assert data["version"] == FORMAT_VERSION == 2 and data["gate"]["features"] == GATED[:2]
    back = ConfidenceModel.from_dict(data, expected=GATED)
    assert back == m
    np.testing.assert_array_equal(back.predict(X), m.predict(X))
    # a gate with a gate, or one that reads what the model does not: refused
    data["gate"] = data["gate"] | {"version": 2, "gate": data["gate"]}
    with pytest.raises(ModelError, match="no gate of its own"):
        ConfidenceModel.from_dict(data)
    stray = m.to_dict()
    stray["gate"]["features"] = ["quality", "margin"]
    with pytest.raises(ModelError, match="the model does not"):
        ConfidenceModel.from_dict(stray)


def test_a_gate_needs_both_kinds_of_rows() -> None:
    X, y, inside = gated_data()
    with pytest.raises(ModelError, match="in-map and off-map"):
        ConfidenceModel.fit_gated(X, y, GATED, np.ones(len(y), bool))
    with pytest.raises(ModelError, match="booleans"):
        ConfidenceModel.fit_gated(X, y, GATED, inside.astype(int))
    with pytest.raises(ModelError, match="all right or all wrong"):
        ConfidenceModel.fit_gated(X, inside, GATED, inside)  # every in-map row right
    with pytest.raises(ModelError, match="not an offset"):
        ConfidenceModel.fit_gated(X[:, 2:], y, GATED[2:], inside, offsets=["map_prior"])
