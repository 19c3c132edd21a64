"""bench/levers/: every lever config parses, builds known methods, keeps the default's
two-tier structure, and no two rows are the same hierarchy (docs/experiments/levers.md is
measured from them)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hmpf.config import build_methods, load_config
from hmpf.methods import Method

ROOT = Path(__file__).resolve().parents[2]
LEVERS = sorted((ROOT / "bench" / "levers").glob("*.yaml"))


def test_there_are_lever_configs() -> None:
    assert len(LEVERS) >= 13


@pytest.mark.parametrize("path", LEVERS, ids=lambda p: p.stem)
def test_lever_config_parses_and_builds(path: Path) -> None:
    text = path.read_text()
    assert text.startswith("# "), "a comment header says which lever and where it was chosen"
    config = load_config(str(path))
    methods = build_methods(config)
    assert set(methods) == set(config.method_ids)
    assert all(isinstance(m, Method) for m in methods.values())
    # Every lever is the default's two-tier structure (plus at most one final-tier method);
    # the levers are measured against default-lite0 (the default until 2026-11-26).
    default = load_config("default-lite0")
    assert [t.k for t in config.tiers] == [t.k for t in default.tiers]
    assert config.weights == default.weights
    assert config.tiers[0].methods == default.tiers[0].methods
    assert set(default.tiers[1].methods) <= set(config.tiers[1].methods)
    assert len(config.tiers[1].methods) - len(default.tiers[1].methods) <= 1


def test_lever_configs_differ_from_the_default_and_each_other() -> None:
    def key(path: str) -> str:
        return load_config(path).model_dump_json(exclude={"name", "description"})

    keys = {p.stem: key(str(p)) for p in LEVERS}
    keys["default"] = key("default")
    keys["default-lite0"] = key("default-lite0")
    assert len(set(keys.values())) == len(keys), "two rows would measure the same hierarchy"
