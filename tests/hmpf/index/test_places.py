"""Places and experiences: the place-level scorer against a brute-force reference, and a real
index version holding fleet experiences read, scored and answered place by place.

The pure part runs on random scores and groupings; the real part builds a small index over
Gardens Point day_right and publishes a version with experience rows (night_right and
day_left frames of some places) through the indexer's own transaction, as a merge does.
"""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from hmpf.config import HierarchyConfig, build_methods, parse_config
from hmpf.features import extract_images
from hmpf.hierarchy import Hierarchy, HierarchyResult, ScoreFn, feature_scorer
from hmpf.imageio import load_image
from hmpf.index import IndexCorruptError, IndexReader, layout
from hmpf.index.places import (
    MIN_PAIRS,
    PAIR_SAMPLE,
    Places,
    PlaceScorer,
    SetAlignment,
    align_pairs,
    augment_rows,
    experience_sets,
    pair_sample,
    place_scorer,
)
from hmpf.index.tables import Ragged, RefTable, columns_from_features, concat_columns
from hmpf.index.thumbnails import make_thumbnails
from hmpf.methods import Method, create_method
from hmpf.methods.base import GlobalMethod
from indexer.build import BuildOptions, NewVersion, VersionTransaction, build

MODES = ["default", "faithful"]


# -- pure: Places, the place scorer, the hierarchy over places --------------------------------


class _Distance(GlobalMethod):
    """A lower-is-better method the scorer reads only ``higher_is_better`` of."""

    name = "test_distance"
    dim = 1
    higher_is_better = False

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return np.zeros(1)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        raise AssertionError("scored through score_fn only")


class _Similarity(_Distance):
    name = "test_similarity"
    higher_is_better = True


METHODS: dict[str, Method] = {"d": _Distance(), "s": _Similarity(), "e": _Distance()}


def _grouping(rng: np.random.Generator, P: int, extra: int) -> np.ndarray:
    """A ``place`` column: P originals (NaN), then ``extra`` experiences of random places."""
    return np.concatenate([np.full(P, np.nan), rng.integers(0, P, extra).astype(np.float64)])


def _raw(rng: np.random.Generator, n: int, ties: bool) -> dict[str, np.ndarray]:
    """Random raw row scores per method (small integers when ``ties``, a NaN or two)."""
    out = {}
    for mid in METHODS:
        x = rng.integers(0, 4, n).astype(np.float64) if ties else rng.normal(size=n)
        x[rng.random(n) < 0.05] = np.nan
        out[mid] = x
    return out


def _row_fn(raw: Mapping[str, np.ndarray]) -> ScoreFn:
    def fn(mid: str, subset: np.ndarray | None) -> np.ndarray:
        return raw[mid].copy() if subset is None else raw[mid][np.asarray(subset, np.int64)]

    return fn


def _brute(
    raw: Mapping[str, np.ndarray], place: np.ndarray, P: int
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Per method and place, explicitly: the best raw score of its rows (max for a similarity,
    min for a distance, NaN only when all are NaN) and the first row holding it (the
    original, then experiences in row order)."""
    place_of = np.where(np.isnan(place), np.arange(len(place)), place).astype(int)
    best, win = {}, {}
    for mid, x in raw.items():
        hib = METHODS[mid].higher_is_better
        b, w = np.full(P, np.nan), np.full(P, -1)
        for p in range(P):
            rows = [r for r in range(len(x)) if place_of[r] == p]
            vals = [x[r] for r in rows if not np.isnan(x[r])]
            if not vals:
                b[p], w[p] = np.nan, rows[0]
                continue
            b[p] = max(vals) if hib else min(vals)
            w[p] = next(r for r in rows if x[r] == b[p])
        best[mid], win[mid] = b, w
    return best, win


@pytest.mark.parametrize("seed", range(6))
def test_place_scorer_equals_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    P, extra = int(rng.integers(1, 30)), int(rng.integers(1, 60))
    place = _grouping(rng, P, extra)
    raw = _raw(rng, P + extra, ties=seed % 2 == 0)
    places = Places.from_column(place, P + extra)
    assert (places.n, places.n_rows, places.has_experiences) == (P, P + extra, True)
    best, win = _brute(raw, place, P)
    for mid in METHODS:
        fn = place_scorer(_row_fn(raw), places, METHODS)
        np.testing.assert_array_equal(fn(mid, None), best[mid])
        np.testing.assert_array_equal(fn.winners[mid], win[mid])
        # A subset of places: unsorted, repeats allowed, as any caller may pass.
        sub = rng.integers(0, P, int(rng.integers(0, 2 * P)))
        fresh = place_scorer(_row_fn(raw), places, METHODS)
        np.testing.assert_array_equal(fresh(mid, sub), best[mid][sub])
        expect = np.full(P, -1)
        expect[sub] = win[mid][sub]
        np.testing.assert_array_equal(fresh.winners.get(mid, np.full(P, -1)), expect)


def _explicit(
    x: np.ndarray,
    P: int,
    place_of: np.ndarray,
    sets: np.ndarray,
    rows: np.ndarray,
    fallback: dict[int, tuple[float, float]] | None = None,
) -> tuple[np.ndarray, dict[int, tuple[float, float]]]:
    """Per place of ``0 .. P-1``, explicitly (higher is better): each set's shift (median of
    its experiences' differences from their places' originals, over ``rows``) and gain
    (sigma / sqrt(2 pi) of the differences, sigma from their MAD); a place's score is the
    best of its original and its shifted experiences, less one gain per experience counted.
    ``fallback``: figures for the sets with too few pairs among ``rows``; a set with neither
    is scored as it is."""
    stats = dict(fallback or {})
    for s in sorted(set(sets[rows].tolist()) - {0}):
        d = np.array([x[r] - x[place_of[r]] for r in rows if sets[r] == s])
        d = d[np.isfinite(d)]
        if len(d) >= MIN_PAIRS:
            shift = float(np.median(d))
            sigma = float(np.median(np.abs(d - shift))) / 0.6744897501960817
            stats[s] = (shift, sigma / np.sqrt(2 * np.pi))
    out = np.empty(P)
    for p in range(P):
        vals, lost = [x[p]], 0.0
        for r in np.flatnonzero(place_of == p):
            if r >= P:
                shift, gain = stats.get(sets[r], (0.0, 0.0))
                vals.append(x[r] - shift)
                lost += gain
        out[p] = max(vals) - lost
    return out, stats


def test_set_shift_removes_what_lifts_a_whole_set() -> None:
    """A set of experiences all lifted by the conditions they were taken in (every score +5)
    does not take the places it covers to the top; the one experience that stands out within
    its set (+3 over the set) still wins its place. Against an explicit computation, for a
    similarity and a distance."""
    rng = np.random.default_rng(3)
    P, extra = 40, 12
    place = np.concatenate([np.full(P, np.nan), np.arange(extra, dtype=np.float64)])
    x = rng.normal(size=P + extra)
    x[P:] += 5.0
    x[P + 7] += 3.0
    raw = {"s": x, "d": -x, "e": -x}
    places = Places.from_column(place, P + extra)
    sets = np.r_[np.zeros(P, np.int64), np.ones(extra, np.int64)]
    expect, stats = _explicit(x, P, places.place_of, sets, np.arange(P + extra))
    assert 4.0 < stats[1][0] < 6.0 and stats[1][1] > 0
    for mid, sign in (("s", 1.0), ("d", -1.0)):
        fn = place_scorer(_row_fn(raw), places, METHODS, sets)
        got = fn(mid, None)
        np.testing.assert_allclose(got, sign * expect)
        best = np.argmax(got) if mid == "s" else np.argmin(got)
        assert best == 7 and fn.winners[mid][7] == P + 7
        # Without the sets, the lifted set takes every place it covers to the top.
        plain = place_scorer(_row_fn(raw), places, METHODS)(mid, None)
        top = np.argsort(-plain if mid == "s" else plain)[:extra]
        assert set(top.tolist()) == set(range(extra))


def test_the_gain_of_extra_images_is_taken_back() -> None:
    """Experiences that show nothing (noise like the originals') lift the places they cover
    by the best-of-two chance alone (about 0.56 sd for normal scores) unless that expected
    gain is taken back: with the sets, covered and uncovered places score alike (averaged
    over 20 maps of 400 places, half of them with one such experience: every pair used)."""
    P, extra = 400, 200
    place = np.concatenate([np.full(P, np.nan), np.arange(extra, dtype=np.float64)])
    places = Places.from_column(place, P + extra)
    sets = np.r_[np.zeros(P, np.int64), np.ones(extra, np.int64)]
    lift = {"plain": [], "fair": []}
    for seed in range(20):
        x = np.random.default_rng(seed).normal(size=P + extra)
        for name, s in (("plain", None), ("fair", sets)):
            got = place_scorer(_row_fn({"s": x}), places, METHODS, s)("s", None)
            lift[name].append(got[:extra].mean() - got[extra:].mean())
    assert np.mean(lift["plain"]) > 0.45
    assert abs(np.mean(lift["fair"])) < 0.05


def _two_sets(seed: int) -> tuple[int, Places, np.ndarray, np.ndarray]:
    """30 places; set 1 covers places 0..9 (lifted by +2), set 2 places 10 and 11."""
    P = 30
    covered = np.r_[np.arange(10), [10, 11]]
    place = np.concatenate([np.full(P, np.nan), covered.astype(np.float64)])
    n = P + len(covered)
    sets = np.r_[np.zeros(P, np.int64), np.ones(10, np.int64), [2, 2]]
    x = np.random.default_rng(seed).normal(size=n)
    x[P : P + 10] += 2.0
    return P, Places.from_column(place, n), sets, x


def _representatives(
    scores: list[np.ndarray], P: int, place_of: np.ndarray, sets: np.ndarray
) -> np.ndarray:
    """Explicitly: per place, the row whose whole-database aligned scores (higher is better),
    each standardised by the median and MAD over every row, sum highest (the first such)."""
    total = np.zeros(len(place_of))
    for x in scores:
        _, whole = _explicit(x, P, place_of, sets, np.arange(len(place_of)))
        a = x - np.array([whole.get(s, (0.0, 0.0))[0] if s else 0.0 for s in sets])
        med = np.median(a)
        total += (a - med) / np.median(np.abs(a - med))
    rows = [np.flatnonzero(place_of == p) for p in range(P)]
    return np.array([r[np.argmax(total[r])] for r in rows])


def _by_representative(
    x: np.ndarray,
    place_of: np.ndarray,
    sets: np.ndarray,
    rows: np.ndarray,
    rep: np.ndarray,
    fallback: dict[int, tuple[float, float]],
) -> np.ndarray:
    """Explicitly: per place, its representative's score less its set's shift (from the
    candidates' ``rows``' pairs, else ``fallback``, else none); no chance gain."""
    _, stats = _explicit(x, len(rep), place_of, sets, rows, fallback=fallback)
    return np.array([x[r] - stats.get(sets[r], (0.0, 0.0))[0] if sets[r] else x[r] for r in rep])


def test_a_later_tier_aligns_on_the_candidates_or_reads_tier_one() -> None:
    """Without a whole-database call (no representatives yet), a call on candidates aligns
    each set on the candidates' own pairs and scores a set with fewer than MIN_PAIRS pairs
    among them as it is. After one, a later tier scores each place by its representative,
    aligned on the candidates' pairs, else on the whole-database figures."""
    P, places, sets, x = _two_sets(5)
    raw = {"s": x, "d": -x, "e": -x}
    cand = place_scorer(_row_fn(raw), places, METHODS, sets)
    assert cand.representatives() is None
    sub = np.array([3, 10, 7, 0, 11])
    rows, _ = places.expand(sub)
    expect, stats = _explicit(x, P, places.place_of, sets, rows)
    assert set(stats) == {1}  # set 2: two pairs, scored as it is
    np.testing.assert_allclose(cand("e", sub), -expect[sub])
    winners = [P + 10 if x[P + 10] > x[10] else 10, P + 11 if x[P + 11] > x[11] else 11]
    assert cand.winners["e"][[10, 11]].tolist() == winners
    # with only two of set 1's places among the candidates, set 1 is taken as it is too
    got = cand("e", np.array([3, 7, 20]))
    np.testing.assert_allclose(got, -np.maximum(x[[3, 7, 20]], np.r_[x[[P + 3, P + 7]], -np.inf]))

    fn = place_scorer(_row_fn(raw), places, METHODS, sets)
    full = fn("s", None)
    _, whole = _explicit(x, P, places.place_of, sets, np.arange(len(x)))
    assert set(whole) == {1}  # set 2: two pairs in all, never placed: scored as it is
    np.testing.assert_allclose(full[10:12], np.maximum(x[10:12], x[P + 10 : P + 12]))
    rep = _representatives([x], P, places.place_of, sets)
    np.testing.assert_array_equal(fn.representatives(), rep)
    sub = np.array([3, 10, 25, 7, 0, 11, 12])
    rows, _ = places.expand(sub)
    # the candidates' pairs of set 1 are places 3, 7 and 0; set 2's (10, 11) are too few
    _, stats = _explicit(x, P, places.place_of, sets, rows, fallback=whole)
    assert stats[1] != whole[1]
    expect = _by_representative(x, places.place_of, sets, rows, rep, whole)
    np.testing.assert_allclose(fn("s", sub), expect[sub])
    np.testing.assert_array_equal(fn.winners["s"][sub], rep[sub])


def test_later_tiers_score_each_place_by_its_representative() -> None:
    """The representative is the row whose standardised aligned tier-1 scores sum highest
    (two methods, one a distance); a later method scores that row alone, without the chance
    gain, whatever its other rows score."""
    P, places, sets, x = _two_sets(8)
    y = np.random.default_rng(9).normal(size=len(x))
    e = np.random.default_rng(10).normal(size=len(x))
    e[P:] += 5.0  # every experience far better for "e": it must not matter
    raw = {"s": x, "d": -y, "e": -e}
    fn = place_scorer(_row_fn(raw), places, METHODS, sets)
    fn("s", None)
    fn("d", None)
    rep = _representatives([x, y], P, places.place_of, sets)
    assert (rep[:12] >= P).any() and (rep[:12] < P).any()  # both kinds represent a place
    np.testing.assert_array_equal(fn.representatives(), rep)
    sub = np.arange(P)
    got = fn("e", sub)
    rows, _ = places.expand(sub)
    np.testing.assert_allclose(got, -_by_representative(e, places.place_of, sets, rows, rep, {}))
    np.testing.assert_array_equal(fn.winners["e"], rep)
    np.testing.assert_array_equal(fn.matched_rows(["e", "s"]), rep)
    # a representative without a score leaves its place unscored, whatever its other rows
    place = int(np.flatnonzero(rep >= P)[0])
    raw["e"][rep[place]] = np.nan
    assert np.isnan(fn("e", np.array([place, 20]))[0])
    # with "s" alone scored whole, on other scores, the representatives follow it alone
    fn2 = place_scorer(_row_fn({"s": y, "d": -y, "e": -e}), places, METHODS, sets)
    fn2("s", None)
    np.testing.assert_array_equal(
        fn2.representatives(), _representatives([y], P, places.place_of, sets)
    )


def test_align_pairs_is_the_median_and_mean_gain() -> None:
    diff = np.array([0.0, 0.0, 1.0, 2.0, 6.0, np.nan, 4.0, 5.0, 3.0, 3.0])
    sets = np.array([0, 0, 1, 1, 1, 1, 2, 2, 3, 3])
    got = align_pairs(diff, sets)
    assert set(got) == {1}  # set 2 and 3: two pairs each, too few
    # median 2, MAD 1 (|d - 2| = 1, 0, 4): gain sigma / sqrt(2 pi), sigma = MAD / 0.6745
    assert got[1].shift == 2.0
    np.testing.assert_allclose(got[1].gain, 1.0 / 0.6744897501960817 / np.sqrt(2 * np.pi))
    assert SetAlignment(2.0, got[1].gain) == got[1]
    assert MIN_PAIRS == 3


def test_pair_sample_spreads_over_each_set() -> None:
    sets = np.r_[np.zeros(50, np.int64), np.full(PAIR_SAMPLE + 100, 1), np.full(7, 2), [1, 3]]
    got = pair_sample(sets)
    assert (sets[got] > 0).all() and len(set(got.tolist())) == len(got)
    ones = got[sets[got] == 1]
    assert len(ones) == PAIR_SAMPLE and ones.min() == 50 and ones.max() == len(sets) - 2
    assert sorted(got[sets[got] == 2].tolist()) == list(
        range(50 + PAIR_SAMPLE + 100, 57 + PAIR_SAMPLE + 100)
    )
    assert got[sets[got] == 3].tolist() == [len(sets) - 1]


def test_experience_sets_are_one_log_vehicle_and_day() -> None:
    day = 86400.0
    place = np.array([np.nan, np.nan, 0, 1, 0, 1, 0])
    refs = RefTable(
        [f"r{i}" for i in range(7)],
        ["0" * 64] * 7,
        {
            "place": place,
            "exp_log": np.array(["", "", "a", "a", "a", "b", "a"], dtype=object),
            "exp_vehicle": np.array(["", "", "v", "v", "w", "v", "v"], dtype=object),
            "exp_time": np.array([np.nan, np.nan, 10, 20, 30, 40, day + 5]),
        },
    )
    places = Places.from_column(place, 7)
    assert experience_sets(refs, places).tolist() == [0, 0, 1, 1, 2, 3, 4]
    assert experience_sets(refs.select(np.arange(2)), Places.identity(2)) is None


def _config(mode: str, tiers: list[tuple[list[str], int]]) -> HierarchyConfig:
    return HierarchyConfig.model_validate(
        {"mode": mode, "tiers": [{"methods": m, "k": k} for m, k in tiers]}
    )


def _same(a: HierarchyResult, b: HierarchyResult) -> None:
    eq = np.testing.assert_array_equal
    assert a.match == b.match
    eq(a.final_candidates, b.final_candidates)
    # the same candidates and answer; the scores come from float32 descriptors the two paths
    # may sum in another order (BLAS threads): equal to float32 rounding (3e-8 relative seen
    # on one machine), not bit for bit
    np.testing.assert_allclose(a.quality, b.quality, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a.combined, b.combined, rtol=1e-6, atol=1e-6)
    for ta, tb in zip(a.tiers, b.tiers, strict=True):
        eq(ta.candidates, tb.candidates)
        for m in ta.scores:
            np.testing.assert_allclose(ta.scores[m], tb.scores[m], rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(ta.raw[m], tb.raw[m], rtol=1e-6, atol=1e-6)


TIERS = [
    [(["d", "s"], 5), (["e", "d"], 3), (["s", "e"], 1)],
    [(["s"], 4), (["d"], 1)],
    [(["d", "e"], 3)],
]


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("tiers", range(len(TIERS)))
def test_hierarchy_over_places_equals_brute_force(mode: str, tiers: int) -> None:
    cfg = _config(mode, TIERS[tiers])
    hier = Hierarchy(cfg, METHODS)
    for seed in range(4):
        rng = np.random.default_rng(100 + seed)
        P, extra = int(rng.integers(8, 40)), int(rng.integers(1, 50))
        place = _grouping(rng, P, extra)
        raw = _raw(rng, P + extra, ties=seed % 2 == 1)
        best, win = _brute(raw, place, P)
        fn = place_scorer(_row_fn(raw), Places.from_column(place, P + extra), METHODS)
        got = hier.run(fn, P)
        _same(got, hier.run(_row_fn(best), P))
        if got.match >= 0:  # the deciding method's winner for the answer's place
            first = cfg.tiers[-1].methods[0]
            rows = fn.matched_rows([m for t in reversed(cfg.tiers) for m in t.methods])
            assert rows[got.match] == win[first][got.match]


@pytest.mark.parametrize("mode", MODES)
def test_one_experience_per_place_equals_the_plain_hierarchy(mode: str) -> None:
    cfg = _config(mode, TIERS[0])
    hier = Hierarchy(cfg, METHODS)
    rng = np.random.default_rng(7)
    raw = _raw(rng, 30, ties=True)
    for places in (Places.identity(30), Places.from_column(np.full(30, np.nan), 30)):
        assert not places.has_experiences
        fn = place_scorer(_row_fn(raw), places, METHODS)
        _same(hier.run(fn, 30), hier.run(_row_fn(raw), 30))
        assert set(fn.matched_rows(["s", "e", "d"])) <= set(range(30))


@pytest.mark.parametrize(
    ("place", "says"),
    [
        ([np.nan, np.nan, 0.0, np.nan], "row 3 is an original reference after experience row 2"),
        ([np.nan, np.nan, 2.0], "names place 2.0"),
        ([np.nan, np.nan, -1.0], "names place -1.0"),
        ([np.nan, np.nan, 0.5], "names place 0.5"),
        ([0.0, np.nan], "row 1 is an original reference"),
    ],
)
def test_a_broken_place_column_is_corrupt(place: list[float], says: str) -> None:
    with pytest.raises(IndexCorruptError, match="refs.h5") as err:
        Places.from_column(np.array(place), len(place), "refs.h5")
    assert says in str(err.value)
    with pytest.raises(IndexCorruptError, match="has"):
        Places.from_column(np.array(place), len(place) + 1, "refs.h5")


def test_augment_rows_puts_an_experience_at_its_place() -> None:
    """With route augmentation (dba) the originals are augmented exactly as without
    experiences, and an experience as if it stood at its place: an experience identical to
    its place's original gets the same augmented row."""
    method = create_method("gist", {"dba": 2})
    assert isinstance(method, GlobalMethod)
    rng = np.random.default_rng(3)
    stored = rng.normal(size=(7, 6)).astype(np.float32)
    place = np.concatenate([np.full(7, np.nan), [4.0, 0.0]])
    rows = np.concatenate([stored[:7], stored[[4, 0]]])
    places = Places.from_column(place, 9)
    out = augment_rows(method, rows, places)
    np.testing.assert_array_equal(out[:7], method.augment_references(stored[:7]))
    np.testing.assert_array_equal(out[7], out[4])
    np.testing.assert_array_equal(out[8], out[0])
    plain = create_method("gist")
    np.testing.assert_array_equal(augment_rows(plain, rows, places), rows)


# -- a real index with experiences ------------------------------------------------------------

CONFIG = {
    "name": "places-test",
    "methods": {"kaze": {"max_keypoints": 40}},
    "tiers": [{"methods": ["hog", "gist"], "k": 4}, {"methods": ["sad", "kaze"], "k": 1}],
}
OPTS = BuildOptions(workers=1, progress=False)
P = 10
#: (traverse, frame, place) of each experience row, in row order.
EXPERIENCES = [
    ("night_right", 2, 2),
    ("night_right", 5, 5),
    ("day_left", 5, 5),
    ("night_right", 8, 8),
]


def publish_experiences(
    index: Path,
    frames: list[tuple[Path, int]],
    *,
    options: BuildOptions = OPTS,
    vehicle: str = "car-7",
) -> str:
    """Publish a version of ``index`` with ``frames`` (image, place) appended as experience
    rows, through the indexer's own transaction (what a merge of fleet frames writes)."""
    tx = VersionTransaction(index, "add")
    with tx, IndexReader(index) as parent:
        paths = [p for p, _ in frames]
        digests = [hashlib.sha256(p.read_bytes()).hexdigest() for p in paths]
        n = len(frames)
        exp = RefTable(
            [f"exp-{parent.version}-{i:03d}-{p.name}" for i, p in enumerate(paths)],
            digests,
            {
                "place": np.array([float(pl) for _, pl in frames]),
                "exp_log": np.array(["log-a"] * n, dtype=object),
                "exp_vehicle": np.array([vehicle] * n, dtype=object),
                "exp_version": np.array([parent.version] * n, dtype=object),
                "exp_time": 1.7e9 + np.arange(n, dtype=np.float64),
                "exp_p_correct": np.full(n, 0.995),
            },
        )
        feats = extract_images(paths, parent.methods, workers=1).features
        cols = {
            mid: concat_columns(parent.columns(mid), columns_from_features(m, feats[mid]))
            for mid, m in parent.methods.items()
        }
        thumbs = make_thumbnails(paths, digests)
        tx.begin({"operation": "add", "parent": parent.version, "test": paths[0].name})
        new = NewVersion(
            parent.config,
            parent.methods,
            parent.refs.concat(exp),
            cols,
            options,
            parent,
            retrain=False,
            thumbnails=Ragged.concat([parent.thumbnail_column(), thumbs]),
        )
        return tx.publish(new, extracted=n).version


@pytest.fixture(scope="module")
def index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """v0001: 10 day_right places; v0002: the same with 4 experiences (places 2, 5, 5, 8)."""
    gp = gardens_point
    base = tmp_path_factory.mktemp("places")
    refs = base / "refs"
    refs.mkdir()
    for p in sorted((gp / "day_right").iterdir())[:P]:
        shutil.copy(p, refs / p.name)
    root = base / "index"
    build(parse_config(CONFIG), refs, root, options=OPTS)
    frames = [(sorted((gp / t).iterdir())[i], pl) for t, i, pl in EXPERIENCES]
    v2 = publish_experiences(root, frames)
    return {"root": root, "refs": sorted(refs.iterdir()), "frames": frames, "v2": v2}


def _reader_features(reader: IndexReader) -> dict[str, Any]:
    """Every row's stored features as a method's reference set (in memory)."""
    rows = np.arange(reader.n_rows)
    db = {}
    for mid, m in reader.methods.items():
        if m.kind == "global":
            db[mid] = np.asarray(reader.global_matrix(mid))
        else:
            db[mid] = m.stack(reader.local_features(mid, rows))
    return db


def _brute_place_fn(
    methods: Mapping[str, Method], rows_fn: ScoreFn, place_of: np.ndarray, n: int
) -> ScoreFn:
    """Per place, explicitly: in a whole-database call the best of its original and its
    shifted experiences, less their expected gain (:func:`_explicit`, aligned on every pair);
    in a later call its representative's score (:func:`_representatives` of the methods
    scored whole), shifted on the candidates' pairs, else on the whole call's figures. One
    experience set here (one log, vehicle and day)."""
    sets = (np.arange(len(place_of)) >= n).astype(np.int64)
    whole: dict[str, np.ndarray] = {}
    everything = np.arange(len(place_of))

    def fn(mid: str, subset: np.ndarray | None) -> np.ndarray:
        sign = 1.0 if methods[mid].higher_is_better else -1.0
        x = sign * np.asarray(rows_fn(mid, None), dtype=np.float64)
        if subset is None:
            whole[mid] = x
            best, _ = _explicit(x, n, place_of, sets, everything)
            return sign * best
        sub = np.asarray(subset, np.int64)
        rows = np.flatnonzero(np.isin(place_of, sub))
        fallback = _explicit(x, n, place_of, sets, everything)[1] if mid in whole else {}
        rep = _representatives(list(whole.values()), n, place_of, sets)
        return sign * _by_representative(x, place_of, sets, rows, rep, fallback)[sub]

    return fn


def test_version_with_experiences_counts_places(index) -> None:
    with IndexReader(index["root"]) as r:
        assert r.version == index["v2"]
        assert (r.n, r.n_rows, len(r), r.has_experiences) == (P, P + 4, P, True)
        assert r.manifest["images"]["count"] == P + 4
        assert r.place_names == [p.name for p in index["refs"]]
        assert r.route_map().n == P
        assert r.reference_profile().n == P
        assert r.faiss_index("hog").ntotal == P + 4
        assert r.global_matrix("gist").shape[0] == P + 4
        assert len(r.thumbnail_column()) == P + 4 and r.thumbnail(P + 3)
        assert len(r.columns("kaze")["descriptors"]) == P + 4
        five = r.experiences(5)
        assert [e.row for e in five] == [5, P + 1, P + 2]
        assert five[0].original and five[0].name == index["refs"][5].name
        assert five[0].vehicle is None and five[0].time is None
        e = five[1]
        assert (e.original, e.place, e.vehicle, e.log, e.version) == (
            False,
            5,
            "car-7",
            "log-a",
            "v0001",
        )
        assert (e.time, e.p_correct) == (1.7e9 + 1, 0.995)
        assert [x.row for x in r.experiences(0)] == [0]


def test_scores_place_by_place_as_brute_force(index) -> None:
    """The index's place-level hierarchy equals one over in-memory row scores reduced per
    place by an explicit loop; a query that is an experience answers its place with it."""
    with IndexReader(index["root"]) as r:
        db = _reader_features(r)
        place_of = r.places.place_of
        hier = r.hierarchy()
        for path, place in index["frames"][1:2] + [(index["refs"][3], 3)]:
            q = r.extract_query(load_image(path))
            fn = r.scorer(q)
            assert isinstance(fn, PlaceScorer)
            got = hier.run(fn, r.n)
            ref = hier.run(
                _brute_place_fn(r.methods, feature_scorer(r.methods, q, db), place_of, r.n), r.n
            )
            _same(got, ref)
            assert got.match == place
            rows = r.matched_rows(fn)
            assert rows is not None and rows.shape == (P,)
            row = int(rows[place])
            expect = P + 1 if path == index["frames"][1][0] else place
            assert row == expect
            assert r.experience(row).name == r.refs.names[expect]


def test_old_version_answers_exactly_as_before(index) -> None:
    """v0001 (no place column) is one experience per place: the row scorer itself, equal to
    in-memory evaluation."""
    with IndexReader(index["root"], "v0001") as r:
        assert (r.n, r.n_rows, r.has_experiences) == (P, P, False)
        assert "place" not in r.refs.meta
        db = _reader_features(r)
        hier = Hierarchy(r.config, build_methods(r.config))
        for path, _ in index["frames"]:
            q = r.extract_query(load_image(path))
            fn = r.scorer(q)
            assert not isinstance(fn, PlaceScorer)
            got = r.hierarchy().run(fn, r.n)
            _same(got, hier.run(feature_scorer(r.methods, q, db), r.n))
            assert r.matched_rows(fn) is None
            assert r.experience(got.match).original


def test_approximate_tier_one_scores_rows_then_places(index, tmp_path) -> None:
    """With an HNSW index for tier 1 the rows are searched, then reduced per place."""
    root = tmp_path / "approx"
    shutil.copytree(index["root"], root)
    layout.set_current(root, "v0001")
    opts = BuildOptions(workers=1, progress=False, faiss={"hog": "HNSW8"})
    publish_experiences(root, index["frames"], options=opts)
    with IndexReader(root) as r:
        assert not r.is_exact("hog") and r.faiss_index("hog").ntotal == P + 4
        path, place = index["frames"][3]
        fn = r.scorer(r.extract_query(load_image(path)))
        got = r.hierarchy().run(fn, r.n)
        assert got.match == place
        rows = r.matched_rows(fn)
        assert rows is not None and rows[place] == P + 3


@pytest.mark.parametrize(
    ("place", "says"),
    [
        (lambda c: np.concatenate([c[:P], [3.0, np.nan, 5.0, 8.0]]), "original reference after"),
        (lambda c: np.concatenate([c[:P], [2.0, 5.0, float(P), 8.0]]), f"names place {P}.0"),
    ],
)
def test_corrupt_place_column_is_refused(index, tmp_path, place, says) -> None:
    root = tmp_path / "bad"
    shutil.copytree(index["root"], root)
    with h5py.File(root / index["v2"] / layout.REFERENCES_H5, "r+") as f:
        col = f["meta"]["place"][()]
        del f["meta"]["place"]
        f["meta"].create_dataset("place", data=place(col))
    with pytest.raises(IndexCorruptError, match="corrupt"):
        IndexReader(root)  # the checksums see it first
    with pytest.raises(IndexCorruptError, match=says) as err:
        IndexReader(root, verify=False)
    assert layout.REFERENCES_H5 in str(err.value)
