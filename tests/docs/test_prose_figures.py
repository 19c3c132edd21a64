"""Decimal figures in the docs' prose come from a record (``bench.pages.unsourced_figures``).

The tables are generated; the prose around them quotes figures by hand. This check holds the
quotes to the records: a decimal figure outside generated blocks and code must be a value of
one of the page's own records (the JSON files in its folder or named on it) or of its
generated blocks, at the precision it is printed with. Settings and versions are listed in
``bench.pages.PROSE_NOT_MEASURED`` with what they are.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench import pages

ROOT = Path(__file__).resolve().parents[2]


def test_every_decimal_figure_in_prose_has_a_record() -> None:
    missing = pages.unsourced_figures(ROOT)
    assert not missing, "figures in prose that no record of their page holds:\n" + "\n".join(
        f"{page}: {fig} in {line!r}" for page, fig, line in missing
    )


def test_each_listed_setting_is_still_quoted_on_its_page() -> None:
    for rel, figures in pages.PROSE_NOT_MEASURED.items():
        text = (ROOT / rel).read_text()
        for fig in figures:
            assert fig in text, f"{rel} no longer quotes {fig}: drop it from PROSE_NOT_MEASURED"


def _page(root: Path, prose: str, record: dict[str, object]) -> None:
    folder = root / "docs" / "experiments" / "x"
    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps(record))
    (folder / "README.md").write_text(prose)
    (root / "README.md").write_text("# nothing measured here\n")


def test_a_figure_its_record_no_longer_holds_is_caught(tmp_path: Path) -> None:
    _page(tmp_path, "Recall@1 was 0.870 and a query took 189.9 ms.\n", {"recall": 0.87})
    missing = pages.unsourced_figures(tmp_path)
    assert [(fig, page) for page, fig, _ in missing] == [("189.9", "docs/experiments/x/README.md")]


def test_rounding_percentages_and_kib_match_their_record(tmp_path: Path) -> None:
    _page(
        tmp_path,
        "It took 189.9 ms, accepted 51.3 % and kept 3.6 KiB per reference.\n",
        {"ms": 189.94, "accepted": 0.5127, "bytes": 3687.7},
    )
    assert pages.unsourced_figures(tmp_path) == []


def test_generated_blocks_and_code_are_not_prose(tmp_path: Path) -> None:
    prose = (
        "<!-- generated: x -->\n| 12.5 |\n<!-- /generated -->\n"
        "```\nlatency 99.9 ms\n```\nThe table says 12.5.\n"
    )
    _page(tmp_path, prose, {})
    assert pages.unsourced_figures(tmp_path) == []
