"""The exported CNN models an index version carries (:mod:`hmpf.index.models`).

On real Gardens Point images, an index with multi-scale GeM and OLO on the bundled
EfficientNet-Lite0 plus Gist:

* the version stores one ONNX model per forward-pass group and input size, listed in the
  manifest's ``models`` and, with its sha256, in ``files``: ``hmpf-index verify`` and every
  reader catch one changed byte in it;
* queries computed from the index run those files in ONNX Runtime without importing torch
  (a subprocess), and their descriptors equal the torch model's (the reference
  implementation, fed by the same numpy / OpenCV preprocessing) within float16 storage
  rounding, with the same answers; the raw maps equal torch's within float32 rounding;
* ``add`` and ``remove`` carry the parent's models over unchanged (hard links);
* a version built before versions stored models is still served (the model exported from
  torch, the same descriptors), and torch's version counts only for such versions.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hmpf.backbones.onnx_runtime import OpenVinoSession
from hmpf.config import build_methods, parse_config
from hmpf.imageio import load_image
from hmpf.index import IndexCorruptError, IndexReader, IndexVersionError
from hmpf.index.models import torch_needed
from hmpf.index.reader import check_packages
from hmpf.methods.base import extract_many
from hmpf.methods.cnn import CnnMethod
from indexer.build import BuildOptions, Summary, add, build, remove
from indexer.maintenance import verify
from tests.conftest import cnn_runtime_as, copy_gp

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

ROOT = Path(__file__).resolve().parents[3]
#: Multi-scale GeM (224 and 128) and OLO (416) on Lite0: three models in two groups.
CONFIG = {
    "name": "onnx-in-index",
    "methods": {"gem": {"scales": [1.0, 0.5]}, "olo": {"regions": 50}},
    "tiers": [{"methods": ["gem", "gist"], "k": 4}, {"methods": ["olo", "gem"], "k": 1}],
}
N_REFS = 12
#: Descriptor values (stored at float16 precision: one step is 4.9e-4 at 0.5) and raw maps
#: (float32, values up to ~30), as between the CNN runtimes
#: (tests/hmpf/methods/test_cnn_runtime.py).
ATOL = 1e-3
MAPS_ATOL = 2e-4
OPTIONS = BuildOptions(workers=1, progress=False)


@pytest.fixture(scope="module")
def built(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``new``: an index with stored models; ``old``: the same, built the way hmpf-index did
    before versions stored models (none); ``refs``: the reference folder."""
    import indexer.build

    base = tmp_path_factory.mktemp("onnx-index")
    refs = copy_gp(gardens_point, "day_right", base / "refs", N_REFS)
    config = parse_config(CONFIG)
    build(config, refs, base / "new", options=OPTIONS)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(indexer.build, "write_models", lambda out, methods: [])
        build(config, refs, base / "old", options=OPTIONS)
    return {"new": base / "new", "old": base / "old", "refs": refs}


@pytest.fixture(scope="module")
def queries(gardens_point: Path) -> list[np.ndarray]:
    return [load_image(p) for p in sorted((gardens_point / "night_right").iterdir())[:N_REFS]]


def _manifest(index: Path, version: str = "v0001") -> dict[str, Any]:
    return json.loads((index / version / "manifest.json").read_text())


def test_version_lists_and_checksums_its_models(built: dict[str, Path]) -> None:
    manifest = _manifest(built["new"])
    models = manifest["models"]
    by_size = {tuple(e["input_size"]): e for e in models}
    assert sorted(by_size) == [(128, 128), (224, 224), (416, 416)]
    assert by_size[(224, 224)]["methods"] == ["gem"] and by_size[(416, 416)]["methods"] == ["olo"]
    assert set(by_size[(416, 416)]["layers"]) == {"head", "s6"}
    for e in models:
        path = built["new"] / "v0001" / e["file"]
        assert e["file"].startswith("onnx/") and path.is_file()
        assert manifest["files"][e["file"]]["bytes"] == path.stat().st_size > 1_000_000
        assert e["backbone"] == "efficientnet_lite0" and e["format"] == "onnx"
        assert e["exporter"]["torch"] == torch.__version__
    assert _manifest(built["old"])["models"] == []
    assert not (built["old"] / "v0001" / "onnx").exists()
    # The models are counted once per version, not per reference, in the build's summary.
    summary = Summary(**manifest["summary"])
    model_bytes = sum(manifest["files"][e["file"]]["bytes"] for e in models)
    assert summary.bytes_models == model_bytes
    line = summary.lines()[1]
    assert f"CNN models {model_bytes / 1e6:.2f} MB, once per version" in line, line
    per_reference = (summary.bytes_total - model_bytes) / summary.images / 1024
    assert f", {per_reference:.1f} KiB per reference" in line, line
    # Every CNN method of a reader runs a stored model: torch's version does not matter.
    with IndexReader(built["new"]) as reader:
        for mid in ("gem", "olo"):
            m = reader.methods[mid]
            assert isinstance(m, CnnMethod) and m.stored_for(m.layers()) is not None
        assert not torch_needed(reader.methods)


def test_a_changed_byte_in_a_model_is_caught(built: dict[str, Path], tmp_path: Path) -> None:
    index = tmp_path / "index"
    shutil.copytree(built["new"], index)
    assert verify(index) == []
    rel = _manifest(index)["models"][0]["file"]
    path = index / "v0001" / rel
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01  # inside the weights, where ONNX Runtime would not notice
    path.write_bytes(bytes(data))
    problems = verify(index)
    assert len(problems) == 1 and rel in problems[0] and "sha256" in problems[0]
    with pytest.raises(IndexCorruptError, match=rel):
        IndexReader(index)


def test_queries_run_the_stored_models_without_importing_torch(
    built: dict[str, Path], gardens_point: Path
) -> None:
    """In a fresh interpreter: open the index as the service does (the engine's
    :class:`~service.engine.Loaded`), answer real night images, and torch was never
    imported; the answers are the in-process ones."""
    nights = sorted((gardens_point / "night_right").iterdir())[2:N_REFS:3]
    with IndexReader(built["new"]) as reader:
        hier = reader.hierarchy()
        want = [
            reader.refs.names[
                hier.run(reader.scorer(reader.extract_query(load_image(p))), reader.n).match
            ]
            for p in nights
        ]
    script = f"""
import sys
from hmpf.imageio import load_image
from service.engine import Loaded
loaded = Loaded.open({str(built["new"])!r}, None)
reader = loaded.reader
for p in {[str(p) for p in nights]!r}:
    feats = reader.extract_query(load_image(p))
    print(reader.refs.names[loaded.hierarchy.run(reader.scorer(feats), reader.n).match])
print("torch" in sys.modules)
"""
    env = {k: v for k, v in os.environ.items() if k != "HMPF_CNN_RUNTIME"}
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [*want, "False"], out.stdout + out.stderr


def _features(reader: IndexReader, images: list[np.ndarray], rt: str) -> list[dict[str, Any]]:
    """Every method's features of ``images``: ``onnx`` through the reader (the version's
    models), ``torch`` by the same methods (config and fitted state) run in torch."""
    if rt == "onnx":
        # ONNX Runtime itself: OpenVINO (what ``auto`` runs on a CPU with AVX-512) can equal
        # torch's maps bit for bit (both on oneDNN), which would leave nothing to compare
        with cnn_runtime_as("onnx"):
            return [reader.extract_query(im) for im in images]
    with cnn_runtime_as("torch"):
        methods = build_methods(reader.config)
        for mid, m in methods.items():
            m.load_state(reader.methods[mid].state_arrays())
        assert all(m.runtime() == "torch" for m in methods.values() if isinstance(m, CnnMethod))
        per_method = extract_many(methods, images)
    return [{mid: per_method[mid][i] for mid in methods} for i in range(len(images))]


def _max_diff(a: Any, b: Any) -> float:
    """Largest absolute difference between two features: arrays, or OLO's regions (its
    visual words are compared apart, :func:`_words_changed`)."""
    if not isinstance(a, np.ndarray):
        a, b = a.regions, b.regions
    assert a.shape == b.shape
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).max())


def _words_changed(a: Any, b: Any) -> float:
    """Fraction of OLO regions whose visual word differs (a region on a word boundary may
    change word under float32 rounding; almost none do)."""
    return float(np.mean(a.words != b.words))


def test_stored_models_give_the_torch_descriptors_and_answers(
    built: dict[str, Path], queries: list[np.ndarray]
) -> None:
    with IndexReader(built["new"]) as reader:
        onnx = _features(reader, queries, "onnx")
        ref = _features(reader, queries, "torch")
        worst = {mid: 0.0 for mid in ("gem", "olo")}
        words = []
        for a, b in zip(onnx, ref, strict=True):
            for mid in worst:
                worst[mid] = max(worst[mid], _max_diff(a[mid], b[mid]))
            words.append(_words_changed(a["olo"], b["olo"]))
        print("max abs descriptor difference, stored ONNX vs torch:", worst, np.mean(words))
        assert max(worst.values()) <= ATOL, worst
        assert float(np.mean(words)) <= 0.01
        # Not vacuous: the runtimes' descriptors are not bit-identical everywhere.
        assert max(worst.values()) > 0.0
        hier = reader.hierarchy()
        for a, b in zip(onnx, ref, strict=True):
            ra, rb = hier.run(reader.scorer(a), reader.n), hier.run(reader.scorer(b), reader.n)
            assert ra.match == rb.match
            # Brute force over the whole database: every reference's score agrees.
            sa, sb = reader.scorer(a)("gem", None), reader.scorer(b)("gem", None)
            np.testing.assert_allclose(sa, sb, atol=2 * ATOL)


def test_stored_maps_equal_torch_maps(built: dict[str, Path], queries: list[np.ndarray]) -> None:
    from hmpf.backbones import load_backbone
    from hmpf.backbones.efficientnet import imagenet_input

    net = load_backbone("efficientnet_lite0")
    with IndexReader(built["new"]) as reader:
        models = {
            m
            for cm in reader.methods.values()
            if isinstance(cm, CnnMethod)
            for m in (cm.stored_models or {}).values()
        }
        assert len(models) == 3
        worst = 0.0
        for model in models:
            x = np.stack([imagenet_input(im, model.size) for im in queries[:4]])
            with cnn_runtime_as("onnx"):  # ONNX Runtime itself (see _features)
                got = model.maps(model.layers)(x)
            with torch.inference_mode():
                want = net.forward_maps(torch.from_numpy(x), model.layers)
            for layer in model.layers:
                assert got[layer].shape == tuple(want[layer].shape)
                worst = max(worst, float(np.abs(got[layer] - want[layer].numpy()).max()))
    print("max abs map difference, stored ONNX vs torch:", worst)
    assert 0.0 < worst <= MAPS_ATOL


def test_add_and_remove_carry_the_models_over(
    built: dict[str, Path], gardens_point: Path, tmp_path: Path, queries: list[np.ndarray]
) -> None:
    index = tmp_path / "index"
    shutil.copytree(built["new"], index)
    more = tmp_path / "more"  # the next three places of the route
    more.mkdir()
    for src in sorted((gardens_point / "day_right").iterdir())[N_REFS : N_REFS + 3]:
        shutil.copy(src, more / src.name)
    add(index, more, options=OPTIONS)
    remove(index, [p.name for p in sorted(more.iterdir())[:1]])
    first = _manifest(index, "v0001")["models"]
    for version in ("v0002", "v0003"):
        assert verify(index, version) == []
        assert _manifest(index, version)["models"] == first
        for e in first:
            a, b = index / "v0001" / e["file"], index / version / e["file"]
            assert a.read_bytes() == b.read_bytes()
            assert a.stat().st_ino == b.stat().st_ino  # linked, not copied
    with IndexReader(index) as reader:
        assert reader.version == "v0003" and reader.n == N_REFS + 2
        result = reader.hierarchy().run(reader.scorer(reader.extract_query(queries[5])), reader.n)
        assert result.match is not None


def test_a_version_without_models_is_served_from_torch(
    built: dict[str, Path], queries: list[np.ndarray]
) -> None:
    """A version built before versions stored models: the reader exports the model from
    torch (installed here) and gives the same features as the stored models."""
    with IndexReader(built["old"]) as old, IndexReader(built["new"]) as new:
        assert old.methods["gem"].stored_models == {}  # type: ignore[attr-defined]
        assert torch_needed(old.methods)
        for im in queries[:4]:
            a, b = old.extract_query(im), new.extract_query(im)
            for mid in ("gem", "olo"):
                assert _max_diff(a[mid], b[mid]) == 0.0  # the same export, run the same way
            assert _words_changed(a["olo"], b["olo"]) == 0.0


def test_torch_version_matters_only_where_torch_runs(built: dict[str, Path]) -> None:
    other_major = {"torch": f"{int(torch.__version__.split('.')[0]) + 1}.0.0"}
    with IndexReader(built["new"]) as reader:
        where = reader.path
        unused = () if torch_needed(reader.methods) else ("torch",)
        assert check_packages(other_major, where, unused) == []
        with cnn_runtime_as("torch"):  # now the forward passes run in torch
            assert torch_needed(reader.methods)
    with IndexReader(built["old"]) as reader:
        assert torch_needed(reader.methods)
    with pytest.raises(IndexVersionError, match="torch"):
        check_packages(other_major, where)


def test_stored_models_in_openvino_give_the_onnx_answers(
    built: dict[str, Path], queries: list[np.ndarray]
) -> None:
    """A server run with ``HMPF_CNN_RUNTIME=openvino`` compiles the version's stored models
    in OpenVINO: the descriptors of ONNX Runtime within float16 storage rounding, the same
    answers."""
    pytest.importorskip("openvino")
    with IndexReader(built["new"]) as reader:
        onnx = _features(reader, queries, "onnx")
    with cnn_runtime_as("openvino"), IndexReader(built["new"]) as reader:
        gem = reader.methods["gem"]
        assert isinstance(gem, CnnMethod) and gem.runtime() == "openvino"
        stored = gem.stored_for(gem.layers())
        assert stored is not None
        assert isinstance(stored[0].maps(gem.layers()).session, OpenVinoSession)
        ov = [reader.extract_query(im) for im in queries]
        hier = reader.hierarchy()
        words = [_words_changed(a["olo"], b["olo"]) for a, b in zip(onnx, ov, strict=True)]
        assert float(np.mean(words)) <= 0.01  # as between ONNX Runtime and torch
        for a, b in zip(onnx, ov, strict=True):
            for mid in ("gem", "olo"):
                assert _max_diff(a[mid], b[mid]) <= ATOL
            ra, rb = hier.run(reader.scorer(a), reader.n), hier.run(reader.scorer(b), reader.n)
            assert ra.match == rb.match


def test_the_service_warm_up_makes_the_sessions_requests_use(
    built: dict[str, Path], monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """``hmpf-serve`` loads a version on its main thread before any request thread has set
    its compute threads; the warm-up must still make the sessions of the requests' thread
    count (else the first request compiles every model again, and both stay in memory)."""
    from hmpf import runtime
    from service.engine import Engine

    monkeypatch.setattr(runtime, "_threads", None)
    monkeypatch.setenv("HMPF_THREADS", "2")  # the process's default: not the workers'
    engine = Engine(built["new"], workers=1, queue=1, threads_per_worker=1)
    try:
        with caplog.at_level("INFO", logger="hmpf.service"):
            loaded = engine.load()
        # the load's log line names what runs the CNN passes (GeM and OLO: the process's)
        assert f"; CNN runtime {runtime.cnn_runtime()})" in caplog.text, caplog.text
        models = [
            m
            for cm in loaded.reader.methods.values()
            if isinstance(cm, CnnMethod)
            for m in (cm.stored_models or {}).values()
        ]
        assert len(models) == 3
        for m in models:
            assert {threads for threads, _ in m._sessions} == {1}, m._sessions
    finally:
        engine.close()
