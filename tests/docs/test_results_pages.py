"""The results pages' generated tables are what their JSON produce (``bench/pages.py``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from bench import pages

ROOT = Path(__file__).resolve().parents[2]


def test_committed_pages_match_their_json() -> None:
    differ = pages.render_all(ROOT, write=False)
    assert not differ, f"pages differ from their JSON (run `python -m bench.pages`): {differ}"


def test_every_block_names_a_known_generator() -> None:
    found = set()
    for page in pages.pages(ROOT):
        found |= {m["name"] for m in pages.BLOCK.finditer(page.read_text())}
    assert found, "no generated block on any results page"
    assert {n for n in found if not n.startswith("presets:")} <= set(pages.GENERATORS)


def _copy(tmp_path: Path) -> Path:
    # the figures too: the experiments reports list the ones their folder holds
    for rel in pages.PAGE_DIRS:
        shutil.copytree(ROOT / rel, tmp_path / rel)
    return tmp_path


@pytest.mark.parametrize(
    ("rel", "path", "value"),
    [
        ("docs/experiments/levers_time_quiet.json", ("rows", "default", "query_ms"), 12.34),
        ("docs/experiments/acceptance/sequence.json", ("routes", "gp_dl_nr", "recall_at_1"), 0.5),
        ("docs/experiments/gp_dl_nr/calibration.json", ("test", "recall_at_1"), 0.123),
    ],
)
def test_check_fails_when_a_json_value_changes(
    tmp_path: Path, rel: str, path: tuple[str, ...], value: float
) -> None:
    root = _copy(tmp_path)
    assert pages.main(["--check", "--root", str(root)]) == 0
    data = json.loads((root / rel).read_text())
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    (root / rel).write_text(json.dumps(data))
    assert pages.render_all(root, write=False)
    assert pages.main(["--check", "--root", str(root)]) == 1
    pages.main(["--root", str(root)])  # regenerating makes the pages agree again
    assert pages.main(["--check", "--root", str(root)]) == 0


def test_presets_line_names_each_preset_with_its_digest() -> None:
    line = pages.render("<!-- generated: presets:default,fast -->\n<!-- /generated -->", ROOT)
    for name in ("default", "fast"):
        assert f"`{name}` (config digest `{pages.preset_digest(name)[:12]}`)" in line


def test_an_unknown_generator_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(KeyError, match="no generator"):
        pages.render("<!-- generated: no.such -->\n<!-- /generated -->", tmp_path)
