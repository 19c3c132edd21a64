"""bench/speed_table.py: its rows are the default and the levers' configs (each another
hierarchy, in the runtime it names), and the routes it scores are the protocols' own
queries and ground truth (Nordland cut to its first frames, not re-indexed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench import speed_table
from bench.harness import protocol_data
from hmpf.config import build_methods, load_config
from hmpf.runtime import CNN_RUNTIME_SETTINGS


def test_rows_are_the_default_and_distinct_levers() -> None:
    def key(which: str) -> str:
        return load_config(which).model_dump_json(exclude={"name", "description"})

    default = key("default")
    levers = {}
    for row, (runtime, which) in speed_table.ROWS.items():
        assert runtime in CNN_RUNTIME_SETTINGS, row
        config = load_config(which)
        assert set(build_methods(config)) == set(config.method_ids)
        if Path(which).suffix == ".yaml":
            assert Path(which).is_file() and runtime == "auto"  # the default runtime
            levers[row] = key(which)
        else:
            assert which in ("default", "fast")
    assert set(speed_table.DEFAULT_ROWS) <= set(speed_table.ROWS)
    assert len(levers) == 6 and default not in levers.values()
    assert len(set(levers.values())) == len(levers), "two rows would measure one hierarchy"


def test_protocols_cut_nordland_to_its_first_frames(gardens_point: Path, nordland: Path) -> None:
    data = speed_table.protocols(50)
    assert list(data) == ["gp_dr_nr", "gp_dl_nr", "gp_dl_dr", speed_table.NORDLAND]
    whole = protocol_data(speed_table.NORDLAND)
    cut = data[speed_table.NORDLAND]
    assert list(cut.reference) == list(whole.reference[:50])
    assert list(cut.query) == list(whole.query[:50])
    np.testing.assert_array_equal(cut.gt, whole.gt[:50, :50])
    assert cut.gt.any(axis=1).all()  # every kept query has a right answer among the kept
    for name in ("gp_dr_nr", "gp_dl_nr", "gp_dl_dr"):
        full = protocol_data(name)
        assert len(data[name].query) == len(full.query) == 200
        np.testing.assert_array_equal(data[name].gt, full.gt)
    assert list(speed_table.protocols(0)) == ["gp_dr_nr", "gp_dl_nr", "gp_dl_dr"]
