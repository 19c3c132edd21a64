"""``hmpf-index build --config auto``: the hierarchy chosen from the references alone, built,
recorded in the version and queried, on real Gardens Point frames.

The choice here searches a pool of cheap methods (no CNN) so it runs in seconds; the choice
itself (determinism, no leak, bounds) is tested in ``tests/hmpf/evaluation/test_auto.py``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from hmpf.config import HierarchyConfig
from hmpf.datasets import list_images
from hmpf.evaluation.calibrate import SearchSpace
from hmpf.evaluation.study import CostModel
from hmpf.features import FeatureCache
from hmpf.imageio import load_image
from hmpf.index import layout
from hmpf.index.reader import IndexReader
from indexer import cli
from indexer.build import build
from tests.conftest import link_frames

METHODS = ("hog", "gist", "sad")
POOL = HierarchyConfig.model_validate(
    {"name": "auto-test-pool", "tiers": [{"methods": list(METHODS), "k": 1}]}
)
COSTS = CostModel(  # fixed: nothing is timed, so the choice is the same under any load
    units={f"extract:{m}": 1.0 for m in METHODS},
    method_units={m: [f"extract:{m}"] for m in METHODS},
    match={m: (0.0, 0.001) for m in METHODS},
    fusion_ms=0.01,
    n_db=40,
)
AUTO: dict[str, Any] = {
    "pool": POOL,
    "space": SearchSpace(METHODS, max_tiers=2, k1=(5, 10), refine=3),
    "costs": COSTS,
    "shelf": ("single-tier",),
    "incumbent": "single-tier",
    "max_queries": 24,
}
N_IMAGES = 40


@pytest.fixture(scope="module")
def refs(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first 40 day_left frames, symlinked into their own folder."""
    return link_frames(
        gardens_point / "day_left", tmp_path_factory.mktemp("auto-build") / "day_left", N_IMAGES
    )


@pytest.fixture(scope="module")
def built(refs: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    index = tmp_path_factory.mktemp("auto-index") / "map"
    cache = FeatureCache(tmp_path_factory.mktemp("auto-build-cache"))
    summary = build("auto", refs, index, seed=4, cache=cache, auto_options=AUTO)
    return index, summary


def test_the_version_records_why_its_config_was_chosen(built: tuple[Path, Any]) -> None:
    index, summary = built
    manifest = layout.read_manifest(index / layout.current_version(index))
    choice = manifest["choice"]
    assert choice["mode"] == "auto" and choice["seed"] == 4
    assert choice["digest"] == manifest["config"]["sha256"]
    assert choice["pool"] == "auto-test-pool"
    assert choice["candidates"] and choice["chosen"]["why"]
    assert choice["sample"]["references"] <= N_IMAGES
    # the summary the command prints says what was chosen and how long it took
    line = next(x for x in summary.lines() if x.startswith("config auto"))
    assert choice["chosen"]["hierarchy"] in line and "seed 4" in line


def test_the_built_version_answers_queries_with_its_fitted_acceptance(
    built: tuple[Path, Any], gardens_point: Path
) -> None:
    index, _ = built
    with IndexReader(index) as reader:
        assert reader.config.acceptance is not None  # fitted on the pseudo-queries
        hier = reader.hierarchy()
        queries = list_images(gardens_point / "day_right")
        right = 0
        for i in range(5, 35, 5):
            feats = reader.extract_query(load_image(queries[i]))
            match = hier.run(reader.scorer(feats), reader.n).match
            right += abs(match - i) <= 2
    assert right >= 4  # day_left -> day_right, +-2 frames: the cheap pool gets most


def test_the_choice_is_deterministic_for_a_seed(
    built: tuple[Path, Any], refs: Path, tmp_path: Path
) -> None:
    index, _ = built
    first = layout.read_manifest(index / layout.current_version(index))
    again = tmp_path / "again"
    cache = FeatureCache(tmp_path / "cache")
    build("auto", refs, again, seed=4, cache=cache, auto_options=AUTO)
    second = layout.read_manifest(again / layout.current_version(again))
    assert second["config"]["sha256"] == first["config"]["sha256"]
    assert second["choice"]["candidates"] == first["choice"]["candidates"]


def test_hmpf_index_info_shows_the_choice(
    built: tuple[Path, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    index, _ = built
    assert cli.main(["info", "--index", str(index)]) == 0
    out = capsys.readouterr().out
    assert "chosen by --config auto (seed 4" in out
    assert cli.main(["info", "--index", str(index), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["choice"]["seed"] == 4


def test_bad_input_fails_before_the_choice(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    code = cli.main(
        ["build", "--config", "auto", "--images", str(empty), "--index", str(tmp_path / "m")]
    )
    assert code == 2
    assert not (tmp_path / "m" / layout.CURRENT).exists()


def test_the_choice_options_need_config_auto(
    refs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["build", "--config", "single-tier", "--images", str(refs), "--index", str(tmp_path)]
    assert cli.main([*argv, "--seed", "3"]) == 2
    assert "go with --config auto" in capsys.readouterr().err
