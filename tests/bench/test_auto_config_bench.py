"""Pieces of ``bench.auto_config``: the mirror images that take ``--time`` past the two
Nordland drives, the size rule's row of the report (the search measured beside it), and the
provenance ``--resume`` keeps for rows an earlier run measured."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from bench.auto_config import mirror_images, resumed, timing_markdown
from bench.pages import auto_config_tables
from hmpf.datasets import list_images


def test_mirror_images_are_the_drives_flipped(nordland: Path, tmp_path: Path) -> None:
    src = list_images(nordland / "summer")[:3]
    out = mirror_images(src, tmp_path)
    assert len(out) == 3 and len({p.name for p in out}) == 3
    for a, b in zip(src, out, strict=True):
        original, flipped = cv2.imread(str(a)), cv2.imread(str(b))
        assert flipped.shape == original.shape
        # written as the source's format: JPEG re-encodes, so close, not equal
        diff = np.abs(flipped.astype(int) - cv2.flip(original, 1).astype(int))
        assert diff.mean() < 8


def _route(**extra: object) -> dict[str, object]:
    flags = {"wins": 0, "losses": 0, "p": 1.0}
    rho = {"n": 3, "spearman_test": 0.5, "spearman_train": 0.25}
    return {
        "route": "nordland_s_w",
        "recall_at_1": {"auto": 0.6, "default": 0.2, "calibrate": 0.55, "auto_without_rule": 0.3},
        "vs": {"default": flags, "oracle": flags, "calibrate": flags},
        "presets": {"thumbnails": 0.6},
        "oracle": "thumbnails",
        "auto_hierarchy": "thumbnails",
        "goals": {"nordland_at_least_0.58": True},
        "correlation": {"candidates": rho, "spread": rho},
        **extra,
    }


def test_the_report_says_what_the_size_rule_skipped_and_the_presets_left_out() -> None:
    unruled = {
        "hierarchy": "search",
        "why": "it won",
        "vs_auto": {"wins": 1, "losses": 9, "p": 0.02},
    }
    text = auto_config_tables(
        {"routes": {"nordland_s_w": _route(auto_without_rule=unruled, presets_skipped=["x"])}}
    )
    assert "search 0.300 against auto's 0.600 (1/9, p 0.02)" in text
    assert "Presets left out of the oracle: nordland_s_w: x." in text
    plain = auto_config_tables({"routes": {"nordland_s_w": _route()}})
    assert "size rule" not in plain and "left out" not in plain


def _timing_row(n: int, **extra: object) -> dict[str, object]:
    steps = ("fit_s", "make_s", "extract_s", "score_s", "search_s", "check_s", "acceptance_s")
    return {
        "references": n,
        "wall_s": 100.0,
        "steps_s": dict.fromkeys(steps, 1.0),
        "sample": {"map": min(n, 1000), "pseudo_queries": 400},
        "load_start": [1.0],
        "load_end": [1.0],
        **extra,
    }


def test_resumed_timing_rows_keep_the_machine_and_date_that_measured_them(tmp_path: Path) -> None:
    head = {"date": "2026-01-01T00:00:00", "commit": "aaa", "machine": "old host"}
    earlier = tmp_path / "timing.json"
    earlier.write_text(json.dumps({**head, "timing": {"1000": _timing_row(1000)}}))
    old = resumed(earlier, "timing")
    assert old["1000"]["measured"] == head
    now = {"date": "2026-02-02T00:00:00", "commit": "bbb", "machine": "new host"}
    record = {
        **now,
        "note": "one process",
        "arguments": {"seed": 0},
        "timing": {**old, "10000": _timing_row(10000, measured=now)},
    }
    rows = [line for line in timing_markdown(record).splitlines() if line.startswith("| 10")]
    assert rows[0].endswith("| old host, 2026-01-01 |")
    assert rows[1].endswith("| new host, 2026-02-02 |")
    # routes: only the protocols asked for are kept
    earlier.write_text(json.dumps({**head, "routes": {"a": {}, "b": {}}}))
    assert list(resumed(earlier, "routes", ["b"])) == ["b"]
