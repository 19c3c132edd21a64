"""bench/map_prior.py on synthetic answers: the map prior enters both models as an offset,
and the stay threshold it chooses keeps the target precision on the training drives as
decided (or falls back to the entry threshold)."""

from __future__ import annotations

import numpy as np

from bench import map_prior as mp
from bench import shipped_acceptance as sa
from hmpf.evaluation.acceptance import Answers, RoutePart
from hmpf.sequence import Estimate


def _answers(correct: np.ndarray, rng: np.random.Generator, prior: float) -> Answers:
    n = len(correct)
    names = sorted({*sa.SEQUENCE_FEATURES, *sa.SINGLE_FEATURES})
    feats = [{k: float(rng.normal(1.5 * (2 * c - 1), 1.0)) for k in names} for c in correct]
    answers = Answers(
        feats,
        correct,
        np.zeros(n),
        np.arange(n),
        [Estimate(i % 50, 0.9, False, i + 1, continuous=i > 0) for i in range(n)],
        np.zeros(n, np.int64),
    )
    for f in answers.features:  # a property of the map: the same in every answer
        f["map_prior"] = prior
    return answers


def _parts(rng: np.random.Generator) -> list[tuple[RoutePart, RoutePart]]:
    parts = []
    for name, rate, prior in (("a", 0.8, 1.2), ("b", 0.75, 1.1), ("c", 0.2, -1.5)):
        y = rng.random(200) < rate
        part = RoutePart(name, _answers(y, rng, prior), _answers(np.zeros(60, bool), rng, prior))
        parts.append((part, part))
    return parts


def test_the_prior_is_an_offset_in_both_models():
    parts = _parts(np.random.default_rng(0))
    plain = (sa.SINGLE_FEATURES, sa.SEQUENCE_FEATURES)
    with_prior = (plain[0] + ("map_prior",), plain[1] + ("map_prior",))
    policy, _ = mp.fit_variant(parts, with_prior, stay=False)
    for model in (policy.model, policy.sequence_model):
        assert model is not None
        j = model.features.index("map_prior")
        assert (model.mean[j], model.scale[j], model.coef[j]) == (0.0, 1.0, 1.0)


def test_the_chosen_stay_keeps_the_target_on_the_training_drives():
    parts = _parts(np.random.default_rng(1))
    with_prior = (sa.SINGLE_FEATURES + ("map_prior",), sa.SEQUENCE_FEATURES + ("map_prior",))
    policy, train = mp.fit_variant(parts, with_prior, stay=True)
    entry = policy.sequence_threshold
    stay = policy.sequence_stay_threshold
    assert entry is not None and stay is not None
    assert stay == train["stay_threshold"] <= entry
    choice = train["stay_choice"]
    assert choice["stay_threshold"] == stay
    tried = list(choice["tried"])
    # stays are tried lowest first, each one below the chosen failed the target
    assert [float(t) for t in tried] == sorted(float(t) for t in tried)
    for key in tried[:-1]:
        precisions = [r["with_stay"]["precision"] for r in choice["tried"][key].values()]
        assert min(p for p in precisions if p is not None) < sa.TARGET
    last = [r["with_stay"]["precision"] for r in choice["tried"][tried[-1]].values()]
    if stay != entry:
        assert min(p for p in last if p is not None) >= sa.TARGET


def test_every_route_threshold_is_the_lowest_that_holds_on_each_route():
    parts = _parts(np.random.default_rng(2))
    seqs = [p[1] for p in parts]
    with_prior = (sa.SINGLE_FEATURES + ("map_prior",), sa.SEQUENCE_FEATURES + ("map_prior",))
    policy, _ = mp.fit_variant(parts, with_prior, stay=False)
    t = mp.every_route_threshold(seqs, policy)
    assert policy.sequence_model is not None
    pred, y, g, inside = sa.route_out_of_fold(
        seqs, policy.sequence_model.features, outside_share=sa.OFF_SHARE, by="folds"
    )
    p, y, g = pred[inside], y[inside].astype(bool), g[inside]

    def holds(x: float) -> bool:
        acc = p >= x
        return all(y[acc & (g == k)].mean() >= sa.TARGET for k in np.unique(g[acc]))

    assert holds(t)
    below = p[p < t]
    if len(below):
        assert not holds(float(below.max()))


def test_a_fixed_stay_is_that_threshold_capped_by_the_entry_threshold():
    parts = _parts(np.random.default_rng(3))
    with_prior = (sa.SINGLE_FEATURES + ("map_prior",), sa.SEQUENCE_FEATURES + ("map_prior",))
    shipped, _ = mp.fit_variant(parts, with_prior, stay=False)
    entry = shipped.sequence_threshold
    assert entry is not None
    for asked in (0.3, mp.HIGH_STAY, 1.0):
        policy, train = mp.fit_variant(parts, with_prior, stay=asked)
        assert policy.sequence_threshold == entry  # the entry threshold is not touched
        assert policy.sequence_stay_threshold == train["stay_threshold"] == min(asked, entry)


def test_the_whole_traverse_table_lists_wrong_frames_as_ranges():
    from bench.pages import _frame_list

    assert _frame_list([]) == "none"
    assert _frame_list([77, 78, 124, 125, 126, 168]) == "77-78, 124-126, 168"
    many = [i * 3 for i in range(14)]  # 14 separate frames
    assert _frame_list(many, most=12).endswith("30, 33 (+2 more)")
