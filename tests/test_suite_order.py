"""The suite's own arrangement (tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.conftest import LONG_FILES, pytest_collection_modifyitems

ROOT = Path(__file__).resolve().parents[1]


class Item:
    """What the collection hook reads of a test."""

    def __init__(self, nodeid: str) -> None:
        self.nodeid = nodeid
        self.fixturenames: tuple[str, ...] = ()

    def add_marker(self, marker: Any) -> None:
        raise AssertionError("no dataset fixture here")


def test_the_long_files_run_first_exist() -> None:
    """A renamed or removed long file would no longer be moved to the front: name it again."""
    missing = [name for name in LONG_FILES if not (ROOT / name).is_file()]
    assert not missing, missing
    assert len(set(LONG_FILES)) == len(LONG_FILES)


def test_long_files_go_first_in_their_order_and_the_rest_keep_theirs() -> None:
    ids = ["tests/a.py::t1", f"{LONG_FILES[1]}::t", "tests/b.py::t", f"{LONG_FILES[0]}::t"]
    items = [Item(i) for i in ids]
    pytest_collection_modifyitems(None, items)  # type: ignore[arg-type]
    assert [i.nodeid for i in items] == [ids[3], ids[1], ids[0], ids[2]]


def test_two_tests_with_one_id_stop_the_run() -> None:
    """pytest-xdist would run one of them (it happened: schemathesis' cases under pytest 9)."""
    items = [Item("tests/a.py::t"), Item("tests/a.py::t"), Item("tests/a.py::u")]
    with pytest.raises(pytest.UsageError, match=r"tests/a\.py::t'\]"):
        pytest_collection_modifyitems(None, items)  # type: ignore[arg-type]
