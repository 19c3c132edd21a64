"""Fixtures of the indexer tests."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from hmpf.config import parse_config
from indexer.build import BuildOptions, build
from tests.conftest import SMALL_INDEX_CONFIG, write_synthetic_images


@pytest.fixture
def index(tmp_path: Path) -> Path:
    """A small index (the small config) of 3 synthetic images, built in ``tmp_path``."""
    refs = write_synthetic_images(tmp_path / "refs", 3)
    root = tmp_path / "index"
    build(
        parse_config(yaml.safe_load(SMALL_INDEX_CONFIG)),
        refs,
        root,
        options=BuildOptions(workers=1, progress=False),
    )
    return root
