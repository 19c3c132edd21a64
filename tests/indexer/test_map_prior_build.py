"""``hmpf-index build --map-prior``: the config's recall@1 on pseudo-queries of the references,
stored in the version's manifest, read back by the reader, carried to derived versions, and
absent (with the reason) where no pseudo-query can be made. Real Gardens Point frames, a
cheap handcrafted config (HOG + Gist), so the pseudo-queries extract in seconds."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from hmpf.config import AcceptanceSettings, load_config
from hmpf.datasets import list_images
from hmpf.evaluation.auto import map_prior
from hmpf.index import layout
from hmpf.index.layout import IndexCorruptError
from hmpf.index.reader import IndexReader
from indexer import cli
from indexer.build import BuildOptions, add, build, prior_note
from tests.conftest import link_frames, write_synthetic_images

#: A single-frame confidence model that reads the map's prior.
_READS_PRIOR = {
    "format": "hmpf-confidence", "version": 1, "features": ["quality", "map_prior"],
    "mean": [0.0, 0.0], "scale": [1.0, 1.0], "coef": [1.0, 1.0], "intercept": 0.0, "l2": 1.0,
}  # fmt: skip
N_IMAGES = 40  # enough along one route for a pseudo-query plan, always
CONFIG = "single-tier"


@pytest.fixture(scope="module")
def refs(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return link_frames(
        gardens_point / "day_left", tmp_path_factory.mktemp("prior-refs") / "day_left", N_IMAGES
    )


@pytest.fixture(scope="module")
def built(refs: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    index = tmp_path_factory.mktemp("prior-index") / "map"
    opts = BuildOptions(workers=1, progress=False)
    build(CONFIG, refs, index, options=opts, with_map_prior=True)
    return index


def _manifest(index: Path) -> dict[str, Any]:
    return layout.read_manifest(index / layout.current_version(index))


def test_the_stored_prior_is_the_configs_pseudo_query_recall_on_the_references(
    built: Path, refs: Path
) -> None:
    manifest = _manifest(built)
    entry = manifest["map_prior"]
    config = load_config(CONFIG)
    assert entry["config_sha256"] == config.digest() == manifest["config"]["sha256"]
    assert entry["references"] == N_IMAGES and entry["pseudo_queries"] > 0
    # the same computation run apart from the build gives the same recall (same seed)
    direct = map_prior(config, list_images(refs), workers=1)
    assert entry["recall_at_1"] == direct["recall_at_1"]
    assert entry["pseudo_queries"] == direct["pseudo_queries"]
    r, n = entry["recall_at_1"], entry["pseudo_queries"]
    kept = min(max(r, 0.5 / n), 1 - 0.5 / n)
    assert entry["map_prior"] == pytest.approx(math.log(kept / (1 - kept)), abs=1e-12)
    with IndexReader(built) as reader:
        assert reader.map_prior() == pytest.approx(entry["map_prior"], abs=0)
        # every answer against the version gets it through the references' profile
        assert reader.reference_profile().map_prior == reader.map_prior()


def test_a_version_derived_from_it_carries_the_prior_and_says_where_it_was_computed(
    built: Path, gardens_point: Path, tmp_path: Path
) -> None:
    more = link_frames(gardens_point / "day_left", tmp_path / "more", 3, start=N_IMAGES)
    parent = layout.current_version(built)
    add(built, more, options=BuildOptions(workers=1, progress=False))
    child = _manifest(built)
    assert child["parent"] == parent
    assert child["map_prior"]["computed_in"] == parent
    parent_entry = layout.read_manifest(built / parent)["map_prior"]
    assert {k: v for k, v in child["map_prior"].items() if k != "computed_in"} == parent_entry
    with IndexReader(built) as reader:
        assert reader.map_prior() == parent_entry["map_prior"]


def test_without_the_option_or_with_too_few_references_there_is_no_value(
    tmp_path: Path, refs: Path
) -> None:
    opts = BuildOptions(workers=1, progress=False)
    plain = tmp_path / "plain"
    build(CONFIG, refs, plain, options=opts)
    assert "map_prior" not in _manifest(plain)
    with IndexReader(plain) as reader:
        assert reader.map_prior() is None
    few = tmp_path / "few"
    build(CONFIG, write_synthetic_images(tmp_path / "three", 3), few, options=opts,
          with_map_prior=True)  # fmt: skip
    entry = _manifest(few)["map_prior"]
    assert entry["map_prior"] is None and "too few references" in entry["why_none"]
    with IndexReader(few) as reader:
        assert reader.map_prior() is None


def test_the_reader_refuses_a_prior_that_is_not_a_finite_number(built: Path) -> None:
    with IndexReader(built) as reader:
        for bad in (float("nan"), float("inf"), "1.2", True):
            reader.manifest["map_prior"] = {**reader.manifest["map_prior"], "map_prior": bad}
            with pytest.raises(IndexCorruptError, match="map_prior"):
                reader.map_prior()
        # computed under another config: not this version's prior
        reader.manifest["map_prior"] = {"config_sha256": "0" * 64, "map_prior": 1.0}
        assert reader.map_prior() is None


def test_the_command_stores_it_and_info_shows_it(
    refs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    index = tmp_path / "cli"
    argv = ["build", "--config", CONFIG, "--images", str(refs), "--index", str(index)]
    assert cli.main([*argv, "--map-prior", "--no-cache", "--workers", "1", "--quiet"]) == 0
    entry = _manifest(index)["map_prior"]
    capsys.readouterr()
    assert cli.main(["info", "--index", str(index)]) == 0
    out = capsys.readouterr().out
    assert f"map prior {entry['map_prior']:+.2f}" in out
    assert f"recall@1 {entry['recall_at_1']:.3f} on {entry['pseudo_queries']} pseudo" in out
    # the cache options now go with the map prior too, not with a build that skips it
    assert cli.main([*argv, "--no-map-prior", "--no-cache"]) == 2
    assert "map prior" in capsys.readouterr().err


def test_a_config_whose_models_read_the_prior_gets_it_without_asking(
    refs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "reads.json"
    doc = load_config(CONFIG).model_dump(mode="json", exclude_none=True)
    doc["acceptance"] = {"threshold": 2.0, "model": _READS_PRIOR, "model_threshold": 0.9}
    config.write_text(json.dumps(doc))
    index = tmp_path / "auto"
    argv = ["build", "--config", str(config), "--images", str(refs), "--index", str(index)]
    assert cli.main([*argv, "--no-cache", "--workers", "1", "--quiet"]) == 0
    entry = _manifest(index)["map_prior"]
    assert math.isfinite(entry["map_prior"]) and entry["pseudo_queries"] > 0
    assert "no map prior" not in capsys.readouterr().out
    # --no-map-prior skips it, and the build says what serving will do
    skipped = tmp_path / "skipped"
    argv = ["build", "--config", str(config), "--images", str(refs), "--index", str(skipped)]
    assert cli.main([*argv, "--no-map-prior", "--workers", "1", "--quiet"]) == 0
    assert "map_prior" not in _manifest(skipped)
    out = capsys.readouterr().out
    assert "no map prior stored" in out and "refuse" in out


def test_the_build_says_what_serving_does_when_the_models_read_a_prior_it_lacks() -> None:
    plain = load_config(CONFIG)  # no model reads the prior: nothing to say
    assert plain.acceptance is None or not plain.acceptance.reads_map_prior
    assert prior_note(plain, None) is None
    acc = {"threshold": 2.0, "model": _READS_PRIOR, "model_threshold": 0.9}
    reads = plain.model_copy(update={"acceptance": AcceptanceSettings(**acc)})
    safe = plain.model_copy(
        update={"acceptance": AcceptanceSettings(**acc, map_prior_fallback=-2.31)}
    )
    stored = {"map_prior": 1.2}
    for entry, fix in (
        (None, "--map-prior"),
        ({"map_prior": None, "why_none": "too few references"}, "too few references"),
    ):
        refused = prior_note(reads, entry)
        assert refused is not None and "refuse" in refused and fix in refused
        fallback = prior_note(safe, entry)
        assert fallback is not None and "-2.31" in fallback and fix in fallback
    assert prior_note(reads, stored) is None and prior_note(safe, stored) is None
