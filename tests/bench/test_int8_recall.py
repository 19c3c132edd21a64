"""bench/int8_recall.py's pure helpers: the calibration sample, the mixed banks, the node
list kept in float32 and the tables printed from a record (no quantisation, no images)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench import int8_recall as ir
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import ScoreBank


def test_calibration_sample_is_deterministic_and_spread() -> None:
    refs = [Path(f"{i:04d}.png") for i in range(200)]
    pick = ir.calibration_paths(refs, 32)
    assert pick == ir.calibration_paths(refs, 32)
    assert len(pick) == 32 and pick[0] == refs[0] and pick[-1] == refs[-1]
    assert ir.calibration_paths(refs[:5], 32) == refs[:5]


def _bank(value: float) -> ScoreBank:
    gt = np.eye(3, dtype=bool)
    data = EvalData([Path("r")] * 3, [Path("q")] * 3, gt, "frames +-0")
    methods = {m: object() for m in ("gem", "netvlad", "olo", "gist")}
    scores = {m: np.full((3, 3), value) for m in methods}
    feats = {m: (value, [value] * 3) for m in methods}
    return ScoreBank(methods, scores, gt, data, feats)  # type: ignore[arg-type]


def test_mixed_takes_only_the_named_methods_from_int8() -> None:
    fp32, int8 = _bank(0.0), _bank(1.0)
    got = ir.mixed(fp32, int8, ("netvlad",))
    assert got.methods["netvlad"] is int8.methods["netvlad"]
    assert got.methods["gem"] is fp32.methods["gem"]
    assert got.scores["netvlad"][0, 0] == 1.0 and got.scores["gist"][0, 0] == 0.0
    assert got.features["netvlad"][0] == 1.0 and got.features["olo"][0] == 0.0


def test_end_nodes_first_conv_and_output_chains(tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    w = helper.make_tensor("w", TensorProto.FLOAT, [1, 1, 1, 1], [1.0])
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["a"], name="first"),
        helper.make_node("Conv", ["a", "w"], ["b"], name="middle"),
        helper.make_node("Conv", ["b", "w"], ["c"], name="last"),
        helper.make_node("Relu", ["c"], ["y"], name="act"),
    ]
    vi = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, 1, 4, 4]) for n in "xy"]
    graph = helper.make_graph(nodes, "g", [vi[0]], [vi[1]], [w])
    path = tmp_path / "m.onnx"
    onnx.save(helper.make_model(graph), str(path))
    assert ir.end_nodes(path) == ["act", "first", "last"]


def test_tables_render_a_record() -> None:
    test = {"wins": 1, "losses": 2, "p": 1.0}
    fig = {
        "methods": {m: {"fp32": 0.5, "int8": 0.4, "sign_test": test} for m in ir.CNN},
        "hierarchy": {
            "fp32": 0.8,
            **{name: {"int8": 0.7, "sign_test": test} for name in ir.SUBSETS},
        },
    }
    ms = {"median_ms": 10.0, "rounds_ms": [10.0]}
    report = {
        "routes": {"gp_dr_nr": {"variants": {"static": fig}}},
        "pass_ms": {"gem 224x224": {"fp32": ms, "static": {**ms, "median_ms": 5.0}}},
        "query_ms": {
            k: {"total_ms": t, "extract_ms": t, "hierarchy_ms": 1.0, "rounds_total_ms": [t]}
            for k, t in (("fp32", 70.0), ("static", 35.0))
        },
    }
    lines = ir.tables(report)
    assert "| gp_dr_nr | static | netvlad | 0.500 | 0.400 | 1 / 2 | 1 |" in lines
    assert any("static 2.00x" in line for line in lines)
    assert lines[-1].endswith("| 2.00x |")
