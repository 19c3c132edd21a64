"""The suite's own arrangement (tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import LONG_FILES

ROOT = Path(__file__).resolve().parents[1]


def test_the_long_files_run_first_exist() -> None:
    """A renamed or removed long file would no longer be moved to the front: name it again."""
    missing = [name for name in LONG_FILES if not (ROOT / name).is_file()]
    assert not missing, missing
    assert len(set(LONG_FILES)) == len(LONG_FILES)
