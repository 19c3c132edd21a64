"""bench/scan_cost.py: every code type scans the rows it was given and keeps the k nearest,
and the record holds each type's times and bytes per row."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bench import scan_cost


def test_each_type_returns_k_rows_of_its_index() -> None:
    rng = np.random.default_rng(1)
    for _, kind, size in scan_cost.TYPES:
        index, queries = scan_cost.build(kind, size, 500, rng)
        _, ids = index.search(queries[:2], 50)
        assert index.ntotal == 500 and ids.shape == (2, 50)
        assert ((ids >= 0) & (ids < 500)).all() and len(set(ids[0])) == 50


def test_the_record_has_every_type(tmp_path: Path) -> None:
    out = tmp_path / "scan.json"
    scan_cost.main(
        ["--rows", "600", "--k", "16", "--queries", "2", "--rounds", "2", "--json", str(out)]
    )
    rec = json.loads(out.read_text())
    assert rec["rows"] == 600 and rec["k"] == 16 and rec["machine"]
    assert set(rec["types"]) == {name for name, _, _ in scan_cost.TYPES}
    for name, kind, size in scan_cost.TYPES:
        t = rec["types"][name]
        assert len(t["ms"]) == 4 and t["ms_p50"] > 0  # 2 rounds x 2 queries
        assert t["bytes_per_row"] == (
            size // 8 if kind == "binary" else size * (2 if kind == "QT_fp16" else 1)
        )
