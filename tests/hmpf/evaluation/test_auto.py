"""The automatic choice from the references alone: pseudo-queries, their truth, the bank,
``choose_config`` and ``hmpf-calibrate --auto``, on real Gardens Point and Nordland images."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hmpf.cli.calibrate import main as calibrate_main
from hmpf.config import AcceptanceSettings, load_config, parse_config
from hmpf.datasets import list_images
from hmpf.evaluation.auto import (
    SMALL_PRESET,
    SMALL_SIDE,
    _kept_acceptance,
    auto,
    choose_config,
    mask_sources,
    pseudo_bank,
    reference_size,
)
from hmpf.evaluation.calibrate import SearchSpace
from hmpf.evaluation.pseudo import (
    ROLES,
    Transform,
    draw_transform,
    plan,
    pseudo_truth,
    read_metadata_csv,
    route_positions,
)
from hmpf.evaluation.study import CostModel, derive_config
from hmpf.features import FeatureCache
from hmpf.imageio import load_image
from tests.conftest import link_frames

#: Cheap methods only (no CNN): the whole choice runs in seconds.
POOL = {"name": "auto-test-pool", "tiers": [{"methods": ["hog", "gist", "sad"], "k": 1}]}
POOL_YAML = "name: auto-test-pool\ntiers:\n  - {methods: [hog, gist, sad], k: 1}\n"
METHODS = ("hog", "gist", "sad")
COSTS = CostModel(  # fixed: nothing is timed
    units={f"extract:{m}": 1.0 for m in METHODS},
    method_units={m: [f"extract:{m}"] for m in METHODS},
    match={m: (0.0, 0.001) for m in METHODS},
    fusion_ms=0.01,
    n_db=40,
)
SPACE = SearchSpace(METHODS, max_tiers=2, k1=(5, 10), refine=3)
N_IMAGES = 40  # Gardens Point day_right frames: fit 20, search 10, check 10 (blocks of 5)
SMALL: dict[str, Any] = {
    "max_queries": 24,
    "space": SPACE,
    "costs": COSTS,
    "shelf": ("single-tier",),
}


@pytest.fixture(scope="module")
def refs(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first 40 day_right frames, symlinked into their own folder."""
    return link_frames(
        gardens_point / "day_right", tmp_path_factory.mktemp("auto") / "day_right", N_IMAGES
    )


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> FeatureCache:
    return FeatureCache(tmp_path_factory.mktemp("auto-cache"))


# -- pseudo-queries ----------------------------------------------------------------------------


def test_plan_and_changes_are_deterministic_for_a_seed(gardens_point: Path) -> None:
    where = route_positions(200)
    a, b = plan(where, seed=3), plan(where, seed=3)
    assert np.array_equal(a.db, b.db) and np.array_equal(a.sources, b.sources)
    assert a.transforms == b.transforms and np.array_equal(a.gt, b.gt)
    assert plan(where, seed=4).transforms != a.transforms  # the seed draws the changes
    image = load_image(list_images(gardens_point / "night_right")[10])
    t = a.transforms[0]
    out = t.apply(image)
    assert out.shape == image.shape and out.dtype == np.uint8
    assert np.array_equal(out, t.apply(image))  # noise included
    assert not np.array_equal(out, image)
    assert np.array_equal(Transform().apply(image), image)  # the identity changes nothing


def test_every_kind_of_change_is_drawn_within_its_range() -> None:
    ts = [draw_transform(np.random.default_rng([0, i])) for i in range(300)]
    assert all(0.8 <= t.crop <= 0.95 for t in ts)  # always a new view
    assert {t.gain != 1.0 for t in ts} == {True, False}
    assert any(t.night < 1.0 and t.noise > 0 for t in ts)  # night-like, with noise
    assert any(t.gamma != 1.0 for t in ts) and any(t.blur > 0 for t in ts)
    assert any(0.35 <= t.resolution < 1.0 for t in ts)
    # one change of light each
    assert all((t.gain != 1.0) + (t.gamma != 1.0) + (t.night != 1.0) == 1 for t in ts)


def test_the_sample_is_bounded_and_spread_along_the_route() -> None:
    where = route_positions(10_000)
    p = plan(where, seed=1, max_references=600, max_queries=80, stretch=50)
    assert len(p.db) <= 600 and len(p.sources) <= 80
    assert p.db.min() < 1000 and p.db.max() > 9000  # stretches along the whole route
    assert np.all(np.diff(p.db) > 0)  # route order
    runs = np.split(p.db, np.flatnonzero(np.diff(p.db) > 1) + 1)
    assert all(len(r) == 50 for r in runs)  # stretches of consecutive references
    assert set(p.role[p.sources]) <= {"search", "check"}
    assert len(p.fit) == (p.role == "fit").sum() > 0
    s = p.summary()
    assert (s["map"], s["pseudo_queries"], s["references"]) == (len(p.db), len(p.sources), 10_000)
    # a small map: every reference, and several pseudo-queries per source
    small = plan(route_positions(40), max_queries=400, min_queries=60)
    assert len(small.db) == 40 and len(small.sources) == 60


def test_roles_take_turns_in_blocks_along_each_route() -> None:
    seq = np.array(["a"] * 20 + ["b"] * 20, dtype=object)
    ts = np.r_[np.arange(20)[::-1], np.arange(20)].astype(float)  # route a driven backwards
    where = route_positions(40, {"sequence": seq, "timestamp": ts})
    p = plan(where, block=5)
    pos = where.position[p.db]
    assert all(p.role[i] == ROLES[(pos[i] // 5) % 4] for i in range(len(p.db)))
    assert where.position[19] == 0 and where.position[0] == 19  # order by timestamp


def test_right_means_a_neighbour_never_the_source_itself() -> None:
    seq = np.array(["a"] * 10 + ["b"] * 10, dtype=object)
    where = route_positions(20, {"sequence": seq})
    db, src = np.arange(20), np.array([0, 5, 10])
    gt = pseudo_truth(where, db, src, tolerance=2)
    assert gt[0].nonzero()[0].tolist() == [1, 2]
    assert gt[1].nonzero()[0].tolist() == [3, 4, 6, 7]
    assert gt[2].nonzero()[0].tolist() == [11, 12]  # route b only: 8 and 9 are route a
    # with GPS: within the radius (another route passing by counts), never the source
    lat = np.r_[np.linspace(0, 0.001, 10), np.full(10, 0.0)]
    lon = np.r_[np.zeros(10), np.linspace(0.0, 0.001, 10)]
    gps = route_positions(20, {"sequence": seq, "lat": lat, "lon": lon})
    g = pseudo_truth(gps, db, np.array([0]), radius_m=15.0)
    assert not g[0, 0] and g[0, 1] and g[0, 10] and g[0, 11] and not g[0, 5]


def test_metadata_csv(tmp_path: Path) -> None:
    csv = tmp_path / "meta.csv"
    csv.write_text("name,lat,lon,timestamp,sequence\nb.png,1.5,2.5,2024-01-01T00:00:10,r1\n")
    meta = read_metadata_csv(csv, ["a.png", "b.png"])
    assert np.isnan(meta["lat"][0]) and meta["lat"][1] == 1.5
    assert meta["sequence"].tolist() == ["", "r1"]
    assert meta["timestamp"][1] > 1.7e9


# -- no leak -------------------------------------------------------------------------------------


def test_mask_sources_ranks_the_source_last_without_moving_the_others() -> None:
    s = np.array([[0.9, 0.2, 0.5], [0.1, 0.3, 0.8]])
    out = mask_sources(s, np.array([0, 2]), higher_is_better=True)
    assert out.tolist() == [[0.2, 0.2, 0.5], [0.1, 0.3, 0.1]]
    d = mask_sources(s, np.array([0, 2]), higher_is_better=False)
    assert d.tolist() == [[0.5, 0.2, 0.5], [0.1, 0.3, 0.3]]
    assert s[0, 0] == 0.9  # a copy


def test_no_pseudo_query_is_answered_or_counted_right_by_its_own_reference(
    refs: Path, cache: FeatureCache, tmp_path: Path
) -> None:
    paths = list_images(refs)
    p = plan(route_positions(len(paths)), seed=0, max_queries=24)
    pool = parse_config(POOL)
    bank, _ = pseudo_bank(pool, paths, p, tmp_path, cache=cache, workers=1)
    rows = np.arange(bank.n_query)
    assert not bank.gt[rows, p.sources].any()  # never right
    assert bank.gt.any(axis=1).all()  # every pseudo-query has a right neighbour
    for mid, m in bank.methods.items():
        s = bank.scores[mid]
        own = s[rows, p.sources][:, None]
        worst_ok = own <= s if m.higher_is_better else own >= s
        assert worst_ok.all(), mid  # ranked last by every method
    # the fit references are no pseudo-query's source: nothing was fitted on a query's image
    assert not set(p.db[p.sources]) & set(p.fit)
    for tiers in ([(METHODS, 1)], [(("hog", "gist"), 5), (("sad",), 1)]):
        results = bank.results(derive_config(pool, tiers))
        matches = np.array([r.match for r in results])
        assert not np.any(matches == p.sources)  # never the answer
        cands = [r.tiers[0].candidates for r in results]
        if len(tiers) > 1:  # no candidate of a tier passing on fewer than all
            assert not any(src in c for src, c in zip(p.sources, cands, strict=True))
    # the unmasked scores would have found the source itself: the mask is what hides it
    raw = parse_config(POOL)
    assert raw.method_ids == list(METHODS)


# -- the choice ------------------------------------------------------------------------------------


def test_choose_config_is_deterministic_and_says_why(refs: Path, cache: FeatureCache) -> None:
    paths = list_images(refs)
    pool = parse_config(POOL)
    a = auto(paths, seed=5, cache=cache, pool=pool, incumbent="single-tier", **SMALL)
    config, reasons = choose_config(
        paths, seed=5, cache=cache, pool=pool, incumbent="single-tier", **SMALL
    )
    assert config.digest() == a.config.digest() and config.acceptance == a.config.acceptance
    assert reasons["candidates"] == a.reasons["candidates"]
    assert reasons["seed"] == 5 and reasons["sample"]["pseudo_queries"] == 24
    assert reasons["sample"]["map"] == N_IMAGES and reasons["sample"]["fit"] == 20
    names = {c["name"] for c in reasons["candidates"]}
    assert names == {"single-tier", "search"}
    assert all(c["check_recall_at_1"] is not None for c in reasons["candidates"])
    assert reasons["chosen"]["why"] and reasons["incumbent"]["name"] == "single-tier"
    assert reasons["time_s"]["total_s"] > 0 and config.acceptance is not None
    assert json.loads(json.dumps(reasons)) == reasons  # JSON-able as it is
    if reasons["chosen"]["name"] == "single-tier":  # a preset chosen as it ships
        assert config.digest() == load_config("single-tier").digest()


def test_hmpf_calibrate_auto_writes_a_loadable_config(refs: Path, tmp_path: Path) -> None:
    pool = tmp_path / "pool.yaml"
    pool.write_text(POOL_YAML)
    meta = tmp_path / "meta.csv"
    names = [p.name for p in list_images(refs)]
    meta.write_text("name,sequence\n" + "".join(f"{n},walk\n" for n in names))
    out = tmp_path / "out" / "auto.yaml"
    code = calibrate_main(
        [
            "--auto",
            "--references",
            str(refs),
            "--metadata",
            str(meta),
            "--pool",
            str(pool),
            "--max-queries",
            "16",
            "--seed",
            "2",
            "--out",
            str(out),
            "--cache-dir",
            str(tmp_path / "cache"),
            "--workers",
            "1",
            "--quiet",
        ]
    )
    assert code == 0
    config = load_config(out)
    assert config.acceptance is not None and config.tiers
    reasons = json.loads((out.parent / "auto.yaml.reasons.json").read_text())
    assert reasons["seed"] == 2 and reasons["sample"]["metadata"] == ["sequence"]
    assert reasons["digest"] == config.digest() and reasons["candidates"]
    assert "# Written by hmpf-calibrate --auto (seed 2)" in out.read_text()


def test_hmpf_calibrate_auto_needs_references(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        calibrate_main(["--auto"])
    assert exc.value.code == 2
    assert "--references" in capsys.readouterr().err


def test_a_preset_kept_as_it_ships_keeps_its_shipped_models() -> None:
    """The pseudo-query fit replaces no model a preset ships (measured worse on real queries:
    docs/experiments/auto_config/acceptance.md); a hierarchy without shipped models gets it."""
    default = load_config("default")
    shipped = default.acceptance
    assert shipped is not None and shipped.sequence_model is not None
    pseudo = AcceptanceSettings(threshold=1.0, precision=0.99)
    config, source = _kept_acceptance(default, default.model_copy(update={"acceptance": pseudo}))
    assert source == "shipped" and config.acceptance == shipped
    assert config.digest() == default.digest()
    # a found hierarchy: the pseudo-query fit for single frames, the default's sequence model
    found = derive_config(default, [(["gem", "netvlad"], 5), (["olo", "gist"], 1)], name="auto")
    config, source = _kept_acceptance(found, found.model_copy(update={"acceptance": pseudo}))
    acc = config.acceptance
    assert source.startswith("pseudo-queries; sequence: the default preset's") and acc
    assert acc.threshold == 1.0 and acc.model is None
    assert acc.sequence_model == shipped.sequence_model
    assert acc.sequence_threshold == shipped.sequence_threshold
    assert acc.sequence_stay_threshold == shipped.sequence_stay_threshold
    assert acc.sequence_stay_ref_z == shipped.sequence_stay_ref_z is not None
    # no global method in tier 1: no reference profile for the sequence features
    local = derive_config(default, [(["olo"], 5), (["gist"], 1)], name="auto")
    config, source = _kept_acceptance(local, local.model_copy(update={"acceptance": pseudo}))
    assert config.acceptance == pseudo and "lock rule" in source


# -- thumbnails: the size rule ---------------------------------------------------------------


@pytest.fixture(scope="module")
def thumbs(nordland: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first 40 Nordland summer thumbnails (64 x 32), symlinked into their own folder."""
    out = tmp_path_factory.mktemp("thumbs")
    for p in list_images(nordland / "summer")[:N_IMAGES]:
        (out / p.name).symlink_to(p)
    return out


def test_reference_size_is_the_median_width_and_height(refs: Path, thumbs: Path) -> None:
    gp = load_image(list_images(refs)[0]).shape
    assert reference_size(list_images(refs)) == (gp[1], gp[0])
    assert reference_size(list_images(thumbs)) == (64, 32)


def test_thumbnails_take_the_thumbnails_preset_without_a_search(thumbs: Path) -> None:
    config, reasons = choose_config(list_images(thumbs), seed=3)
    assert config.digest() == load_config(SMALL_PRESET).digest() == reasons["digest"]
    assert reasons["rule"] == {
        "image_size": [64, 32],
        "small_side": SMALL_SIDE,
        "preset": SMALL_PRESET,
    }
    assert reasons["evaluated"] == 0 and reasons["candidates"] == []
    assert reasons["chosen"]["hierarchy"] == SMALL_PRESET and "64 x 32" in reasons["chosen"]["why"]
    assert json.loads(json.dumps(reasons)) == reasons
    assert choose_config(list_images(thumbs), seed=4)[0].digest() == config.digest()


def test_the_size_rule_can_be_turned_off(thumbs: Path, cache: FeatureCache) -> None:
    result = auto(
        list_images(thumbs), seed=1, cache=cache, pool=parse_config(POOL), small_side=None, **SMALL
    )
    assert result.bank is not None and result.reasons["evaluated"] > 0
    assert "rule" not in result.reasons and result.reasons["candidates"]


def test_hmpf_calibrate_auto_says_the_rule(thumbs: Path, tmp_path: Path) -> None:
    out = tmp_path / "auto.yaml"
    args = ["--auto", "--references", str(thumbs), "--out", str(out), "--quiet"]
    assert calibrate_main(args) == 0
    assert load_config(out).digest() == load_config(SMALL_PRESET).digest()
    text = out.read_text()
    assert "Chosen: thumbnails" in text and "below 128 px" in text
    assert (tmp_path / "auto.yaml.reasons.json").exists()
