"""The CNN runtimes: ONNX Runtime (the default) and OpenVINO against torch (the reference),
and the cache of exported models.

* Real Gardens Point images, the default hierarchy's CNN methods (gem, netvlad, olo), fitted
  once (torch) and shared by every runtime: the float32 runtimes' (``onnx``, ``openvino``)
  descriptors equal torch's within :data:`ATOL` (they are stored at float16 precision; the
  maps differ by float32 rounding, ~2e-5) and the hierarchy's answers are equal on 30
  references x 30 queries; ``openvino-bf16``'s global descriptors are within
  :data:`BF16_ATOL` and its answers nearly all equal (its recall is measured in
  ``bench.int8_recall``).
* OpenVINO's sessions: the compute threads, calls from several threads at once, a model run
  in a runtime of its own (``StoredModel(runtime=)``), and a missing package.
* The model cache: a second load exports nothing, a changed key exports anew, a corrupt file
  is exported again, an unwritable cache folder falls back to a temporary one.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hmpf import runtime
from hmpf.config import build_methods, load_config
from hmpf.errors import ConfigError, MissingDependencyError
from hmpf.hierarchy import Hierarchy, feature_scorer
from hmpf.imageio import load_image
from hmpf.methods import create_method
from hmpf.methods.base import extract_many, fit_many
from tests.conftest import cnn_runtime_as

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from hmpf.backbones import load_backbone  # noqa: E402
from hmpf.backbones import onnx_runtime as ox  # noqa: E402

#: Largest difference allowed between the runtimes' descriptor values (unit-norm vectors and
#: regions at float16 precision: one float16 step is 2.4e-4 at 0.25, 4.9e-4 at 0.5).
ATOL = 1e-3
#: Largest difference allowed between the runtimes' raw maps (float32, values up to ~30).
MAPS_ATOL = 2e-4
#: ``openvino-bf16`` against the float32 runtimes: bfloat16 keeps 8 bits of mantissa (about
#: 0.4 % per value); measured up to 0.012 on unit-norm NetVLAD vectors.
BF16_ATOL = 0.05
#: The runtimes whose packages are installed (openvino is an extra of its own).
RUNTIMES = [
    r for r in runtime.CNN_RUNTIMES if not r.startswith("openvino") or find_spec("openvino")
]
N = 30  # references and queries of the Gardens Point subset


# -------------------------------------------------------------------- both runtimes, real data


@pytest.fixture(scope="module")
def both(gardens_point: Path) -> dict[str, Any]:
    """The default hierarchy's features of 30 references (day_right) and 30 queries
    (day_left, the same places) under each runtime, from one set of fitted parameters."""
    from hmpf.datasets import list_images

    pick = np.linspace(0, 199, N).round().astype(int)
    refs = [load_image(list_images(gardens_point / "day_right")[i]) for i in pick]
    qrys = [load_image(list_images(gardens_point / "day_left")[i]) for i in pick]
    config = load_config("default")
    methods = build_methods(config)
    cnn = [m for m in methods if getattr(methods[m], "batched", False)]
    # Fitted once, on a third of the references (faster; only the extraction is compared).
    fit_many({m: methods[m] for m in methods if methods[m].requires_fit()}, refs[::3])
    state = {m: methods[m].state_arrays() for m in methods}
    others = {m: methods[m] for m in methods if m not in cnn}
    shared = {k: extract_many(others, imgs) for k, imgs in (("ref", refs), ("qry", qrys))}
    out: dict[str, Any] = {"config": config, "cnn": cnn, "methods": methods}
    for name in RUNTIMES:
        ms = build_methods(config)
        for m, arrays in state.items():
            if arrays:
                ms[m].load_state(arrays)
        with cnn_runtime_as(name):
            assert all(ms[m].runtime() == name for m in cnn)  # type: ignore[attr-defined]
            feats = {
                k: {**extract_many({m: ms[m] for m in cnn}, imgs), **shared[k]}
                for k, imgs in (("ref", refs), ("qry", qrys))
            }
        out[name] = (ms, feats)
    return out


def _answers(config: Any, methods: dict[str, Any], feats: dict[str, Any]) -> list[int]:
    db = {m: methods[m].stack(feats["ref"][m]) for m in methods}
    hierarchy = Hierarchy(config, methods)
    answers = []
    for qi in range(N):
        query = {m: feats["qry"][m][qi] for m in methods}
        answers.append(hierarchy.run(feature_scorer(methods, query, db), N).match)
    return answers


def _worst(both: dict[str, Any], name: str) -> tuple[dict[str, float], float]:
    """Largest descriptor difference per CNN method between runtime ``name`` and torch, and
    the share of OLO regions whose visual word differs."""
    _, ft = both["torch"]
    _, fo = both[name]
    worst, words = {}, []
    for m in both["cnn"]:
        diffs = []
        for part in ("ref", "qry"):
            for a, b in zip(ft[part][m], fo[part][m], strict=True):
                if m == "olo":
                    assert a.regions.shape == b.regions.shape
                    diffs.append(np.abs(a.regions - b.regions).max())
                    words.append(np.mean(a.words != b.words))
                else:
                    assert a.shape == b.shape and a.dtype == b.dtype
                    diffs.append(np.abs(a.astype(np.float32) - b.astype(np.float32)).max())
        worst[m] = float(np.max(diffs))
    return worst, float(np.mean(words))


@pytest.mark.parametrize("name", ["onnx", "openvino", "openvino-bf16"])
def test_descriptors_against_torch(both: dict[str, Any], name: str) -> None:
    if name not in both:
        pytest.skip("openvino is not installed (the openvino extra)")
    assert sorted(both["cnn"]) == ["gem", "netvlad", "olo"]
    worst, words = _worst(both, name)
    print(f"max |torch - {name}| per method:", worst, "olo words changed:", words)
    if name != "openvino-bf16":  # float32: the same maps within rounding
        assert max(worst.values()) <= ATOL, worst
        # a region on a visual-word boundary may change word; almost none do
        assert words <= 0.01
    else:  # bfloat16: the global descriptors stay close; OLO's regions and words do not
        # (most of its words change, measured 65 %: a region's word is the nearest of many
        # close words), which is why the answers are compared too, and recall measured
        assert max(worst["gem"], worst["netvlad"]) <= BF16_ATOL, worst


def test_runtimes_give_the_same_answers(both: dict[str, Any]) -> None:
    config = both["config"]
    got = {name: _answers(config, *both[name]) for name in RUNTIMES}
    assert got["onnx"] == got["torch"]
    assert np.mean(np.array(got["onnx"]) == np.arange(N)) >= 0.8  # day -> day: mostly right
    if "openvino" in got:
        assert got["openvino"] == got["onnx"]
        same = np.mean(np.array(got["openvino-bf16"]) == np.array(got["onnx"]))
        assert same >= 0.9, got


def test_maps_equal_torch_at_every_default_size(both: dict[str, Any]) -> None:
    net = load_backbone("efficientnet_lite0")
    rng = np.random.default_rng(0)
    for size, layers in (
        ((224, 224), ["head"]),
        ((288, 512), ["s6"]),
        ((416, 416), ["head", "s6"]),
    ):
        x = rng.standard_normal((3, 3, *size)).astype(np.float32)
        with torch.inference_mode():
            ref = {k: v.numpy() for k, v in net.forward_maps(torch.from_numpy(x), layers).items()}
        maps = ox.onnx_maps(net, layers, size)
        got = maps(x)  # one image per run
        whole = ox.OnnxMaps(maps.session, layers, maps.path, run_batch=3)(x)  # one run of 3
        for k in layers:
            assert got[k].shape == ref[k].shape == whole[k].shape
            np.testing.assert_allclose(got[k], ref[k], rtol=0, atol=MAPS_ATOL)
            np.testing.assert_allclose(whole[k], got[k], rtol=0, atol=1e-5)


# --------------------------------------------------------------------------- the setting


def test_runtime_setting_and_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    gem = create_method("gem")
    with cnn_runtime_as("torch"):
        torch_key = gem.descriptor_key()
        assert gem.runtime() == "torch" and torch_key == gem.cache_key()  # the keys it had
    keys = {torch_key}
    for name in ("onnx", "openvino", "openvino-bf16"):
        with cnn_runtime_as(name):
            assert gem.runtime() == name and gem.cache_key() == torch_key
            keys.add(gem.descriptor_key())
    assert len(keys) == 4  # every runtime's descriptors cached apart
    with cnn_runtime_as("onnx"):
        assert create_method("gem", {"device": "cuda"}).runtime() == "torch"  # ORT: CPU only
        vgg = create_method("gem", {"backbone": "vgg16", "weights": "x.pth"})
        assert vgg.runtime() == "torch"  # a backbone not checked under ONNX Runtime
    monkeypatch.setattr(runtime, "_cnn_runtime", None)
    monkeypatch.setenv("HMPF_CNN_RUNTIME", "Torch")
    assert runtime.cnn_runtime() == "torch"
    monkeypatch.delenv("HMPF_CNN_RUNTIME")
    monkeypatch.setattr(runtime, "auto_cnn_runtime", lambda: "openvino-bf16")  # a sentinel
    assert runtime.cnn_runtime() == "openvino-bf16"  # the default: whatever auto chooses
    monkeypatch.setenv("HMPF_CNN_RUNTIME", " Auto ")
    assert runtime.cnn_runtime() == "openvino-bf16"
    monkeypatch.setenv("HMPF_CNN_RUNTIME", "tensorrt")
    with pytest.raises(
        ConfigError,
        match="HMPF_CNN_RUNTIME must be one of auto, onnx, openvino, openvino-bf16, torch",
    ):
        runtime.cnn_runtime()
    with pytest.raises(ConfigError, match="one of"):
        runtime.set_cnn_runtime("jax")


def test_auto_runs_openvino_only_with_avx512_and_the_package() -> None:
    """``auto`` (the default runtime): OpenVINO float32 where it is installed and the CPU has
    AVX-512 (AMX CPUs list avx512f too), ONNX Runtime elsewhere (AVX2 only: no faster)."""
    avx2 = {"sse4_2", "avx", "avx2", "fma"}
    avx512 = avx2 | {"avx512f", "avx512bw", "avx512_vnni"}
    amx = avx512 | {"avx512_bf16", "amx_bf16", "amx_tile"}
    assert runtime.choose_cnn_runtime(avx512, openvino_installed=True) == "openvino"
    assert runtime.choose_cnn_runtime(amx, openvino_installed=True) == "openvino"
    assert runtime.choose_cnn_runtime(avx2, openvino_installed=True) == "onnx"
    assert runtime.choose_cnn_runtime(set(), openvino_installed=True) == "onnx"  # no cpuinfo
    for flags in (avx2, avx512, amx):
        assert runtime.choose_cnn_runtime(flags, openvino_installed=False) == "onnx"


@pytest.fixture
def fresh_auto() -> Iterator[None]:
    """``auto_cnn_runtime`` reads the machine again in the test, and after it."""
    runtime.auto_cnn_runtime.cache_clear()
    yield
    runtime.auto_cnn_runtime.cache_clear()


def test_auto_without_cpuinfo_or_with_a_broken_openvino_runs_onnx(
    fresh_auto: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    import importlib.util

    monkeypatch.setattr(runtime, "_cpuinfo", lambda: {})  # no /proc/cpuinfo (macOS, ARM)
    assert runtime.auto_cnn_runtime() == "onnx"
    runtime.auto_cnn_runtime.cache_clear()
    monkeypatch.setattr(runtime, "_cpuinfo", lambda: {"flags": "avx2 avx512f"})
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: object())  # "installed"
    monkeypatch.setitem(sys.modules, "openvino", None)  # ... but its import fails
    assert runtime.auto_cnn_runtime() == "onnx"
    runtime.auto_cnn_runtime.cache_clear()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)  # not installed
    assert runtime.auto_cnn_runtime() == "onnx"


def test_set_cnn_runtime_auto_passes_the_chosen_runtime_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """``set_cnn_runtime("auto")`` sets the runtime it chose, for the processes it starts."""
    monkeypatch.setattr(runtime, "_cnn_runtime", None)
    monkeypatch.setenv("HMPF_CNN_RUNTIME", "auto")  # restored after the test
    runtime.set_cnn_runtime("auto")
    assert runtime.cnn_runtime() == runtime.auto_cnn_runtime() != "auto"
    assert os.environ["HMPF_CNN_RUNTIME"] == runtime.auto_cnn_runtime()


def test_shared_forward_pass_per_group_onnx(monkeypatch: pytest.MonkeyPatch) -> None:
    """Under ONNX Runtime too, methods sharing a group key share one run per batch."""
    gem = create_method("gem", {"input_size": [416, 416]})
    hyb = create_method("hybridnet")  # s6 at 416 x 416: same group as gem above
    other = create_method("gem", {"input_size": [96, 96]})
    calls: list[tuple[int, tuple[str, ...]]] = []
    original = ox.OnnxMaps.__call__

    def counting(self: ox.OnnxMaps, batch: np.ndarray) -> dict[str, np.ndarray]:
        calls.append((batch.shape[0], tuple(sorted(self.layers))))
        return original(self, batch)

    monkeypatch.setattr(ox.OnnxMaps, "__call__", counting)
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 255, (120, 160, 3), dtype=np.uint8) for _ in range(3)]
    with cnn_runtime_as("onnx"):
        out = extract_many({"g": gem, "h": hyb, "o": other}, images)
    assert sorted(calls) == [(3, ("head",)), (3, ("head", "s6"))]
    assert len(out["g"]) == len(out["h"]) == len(out["o"]) == 3


# ------------------------------------------------------------------------- the model cache

SIZE = (64, 96)  # small: an export takes about a second


@pytest.fixture
def cache_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fresh model cache; sessions and the fallback folder are forgotten around the test."""
    monkeypatch.setenv("HMPF_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(ox, "_FALLBACK_DIR", None)
    ox.clear_sessions()
    yield tmp_path / "onnx"
    ox.clear_sessions()


@pytest.fixture
def exports(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Paths exported during the test (the export itself still runs)."""
    done: list[Path] = []
    original = ox._export

    def counting(net: Any, layers: Any, size: Any, path: Path) -> None:
        done.append(path)
        original(net, layers, size, path)

    monkeypatch.setattr(ox, "_export", counting)
    return done


def _check_maps(maps: ox.OnnxMaps) -> None:
    net = load_backbone("efficientnet_lite0")
    x = np.random.default_rng(2).standard_normal((2, 3, *SIZE)).astype(np.float32)
    with torch.inference_mode():
        ref = net.forward_maps(torch.from_numpy(x), ["s4"])["s4"].numpy()
    np.testing.assert_allclose(maps(x)["s4"], ref, rtol=0, atol=MAPS_ATOL)


def test_second_load_does_not_export(cache_dir: Path, exports: list[Path]) -> None:
    net = load_backbone("efficientnet_lite0")
    first = ox.onnx_maps(net, ["s4"], SIZE)
    assert exports == [first.path] and first.path.parent == cache_dir
    assert first.path.is_file() and first.path.with_name(first.path.name + ".sha256").is_file()
    assert ox.onnx_maps(net, ["s4"], SIZE) is first  # the session is kept in the process
    ox.clear_sessions()  # as a new process: loads the file
    second = ox.onnx_maps(net, ["s4"], SIZE)
    assert second is not first and second.path == first.path and len(exports) == 1
    _check_maps(second)
    assert sorted(p.name for p in cache_dir.iterdir()) == [
        first.path.name,
        first.path.name + ".sha256",
    ]  # no temporary file left


def test_changed_key_exports_anew(
    cache_dir: Path, exports: list[Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    net = load_backbone("efficientnet_lite0")
    a = ox.onnx_maps(net, ["s4"], SIZE).path
    b = ox.onnx_maps(net, ["s4"], (SIZE[0], SIZE[1] + 32)).path  # another input size
    c = ox.onnx_maps(net, ["s3", "s4"], SIZE).path  # other layers
    monkeypatch.setattr(ox, "EXPORT_VERSION", "test")  # other export settings
    d = ox.onnx_maps(net, ["s4"], SIZE).path
    assert exports == [a, b, c, d] and len({a, b, c, d}) == 4
    # The torch version and the weights are in the key too.
    key = ox.export_key(net, ["s4"], SIZE)
    monkeypatch.setattr(torch, "__version__", "0.0.0")
    assert ox.export_key(net, ["s4"], SIZE) != key
    monkeypatch.setitem(ox._WEIGHTS, net, "0" * 64)
    assert ox.export_key(net, ["s4"], SIZE) != key


@pytest.mark.parametrize("damage", ["truncated", "garbage_with_matching_sha256"])
def test_corrupt_cached_file_is_exported_again(
    cache_dir: Path, exports: list[Path], damage: str
) -> None:
    net = load_backbone("efficientnet_lite0")
    path = ox.onnx_maps(net, ["s4"], SIZE).path
    ox.clear_sessions()
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:1000])
    else:  # the checksum matches, the file does not load
        path.write_bytes(b"not an onnx model")
        path.with_name(path.name + ".sha256").write_text(ox._file_sha256(path))
    maps = ox.onnx_maps(net, ["s4"], SIZE)
    assert exports == [path, path]
    _check_maps(maps)


def test_unwritable_cache_falls_back_to_a_temporary_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, exports: list[Path]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv("HMPF_CACHE_DIR", str(blocker))
    monkeypatch.setattr(ox, "_FALLBACK_DIR", None)
    ox.clear_sessions()
    try:
        maps = ox.onnx_maps(load_backbone("efficientnet_lite0"), ["s4"], SIZE)
        assert ox._FALLBACK_DIR is not None and maps.path.parent == ox._FALLBACK_DIR
        _check_maps(maps)
    finally:
        ox.clear_sessions()


def test_session_threads_follow_compute_threads(
    cache_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    net = load_backbone("efficientnet_lite0")
    monkeypatch.setattr(runtime, "_cnn_runtime", "onnx")  # ONNX Runtime's session options
    monkeypatch.setattr(runtime, "_threads", 1)
    one = ox.onnx_maps(net, ["s4"], SIZE)
    monkeypatch.setattr(runtime, "_threads", 2)
    two = ox.onnx_maps(net, ["s4"], SIZE)
    assert one is not two and one.path == two.path
    for maps, n in ((one, 1), (two, 2)):
        opts = maps.session.get_session_options()
        assert opts.intra_op_num_threads == n and opts.inter_op_num_threads == 1
        assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"


# ------------------------------------------------------------------------------ OpenVINO


def test_openvino_sessions(cache_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An exported model in OpenVINO: the maps of ONNX Runtime (float32), the compute
    threads, one session per runtime, calls from several threads at once, and a model run in
    a runtime of its own whatever the process's."""
    pytest.importorskip("openvino")
    net = load_backbone("efficientnet_lite0")
    x = np.random.default_rng(3).standard_normal((3, 3, *SIZE)).astype(np.float32)
    want = ox.onnx_maps(net, ["s4"], SIZE)(x)["s4"]
    for threads in (1, 2):
        monkeypatch.setattr(runtime, "_threads", threads)
        with cnn_runtime_as("openvino"):
            maps = ox.onnx_maps(net, ["s4"], SIZE)
        assert isinstance(maps.session, ox.OpenVinoSession)
        assert int(maps.session.compiled.get_property("INFERENCE_NUM_THREADS")) == threads
        np.testing.assert_allclose(maps(x)["s4"], want, rtol=0, atol=MAPS_ATOL)
    with ThreadPoolExecutor(4) as pool:  # one infer request per thread
        runs = list(pool.map(lambda i: maps(x[i % 3 : i % 3 + 1])["s4"], range(12)))
    for i, got in enumerate(runs):
        np.testing.assert_allclose(got, want[i % 3 : i % 3 + 1], rtol=0, atol=MAPS_ATOL)
    stored = ox.StoredModel(maps.path, ["s4"], SIZE, runtime="openvino-bf16")
    with cnn_runtime_as("onnx"):
        own = stored.maps(["s4"])
        assert isinstance(own.session, ox.OpenVinoSession)
        assert not isinstance(
            ox.StoredModel(maps.path, ["s4"], SIZE).maps(["s4"]).session, ox.OpenVinoSession
        )
    got = own(x)["s4"]
    assert got.shape == want.shape
    # bfloat16: close to float32, relative to the maps' range
    assert np.abs(got - want).max() <= 0.05 * np.abs(want).max()
    with pytest.raises(ValueError, match="runtime must be one of"):
        ox.StoredModel(maps.path, ["s4"], SIZE, runtime="torch")


def test_a_stored_model_with_its_own_runtime_runs_in_it_when_a_method_extracts(
    cache_dir: Path,
) -> None:
    """A method extracting through stored models made with ``runtime=`` (as
    ``bench.int8_recall`` runs the float32 exports in OpenVINO) runs them in that runtime,
    not in the process's: under ``onnx`` the descriptors equal those a process in
    ``openvino-bf16`` computes from the same file, and differ from ONNX Runtime's."""
    pytest.importorskip("openvino")
    size = tuple(SIZE)
    image = np.random.default_rng(5).integers(0, 256, (120, 160, 3), dtype=np.uint8)

    def gem(runtime_of_model: str | None) -> Any:
        m = create_method("gem", {"input_size": list(size)})
        path = ox.onnx_maps(m.backbone(), sorted(m.layers()), size).path
        models = {size: ox.StoredModel(path, sorted(m.layers()), size, runtime=runtime_of_model)}
        m.use_stored_models(models, cache_dir)
        return m

    with cnn_runtime_as("onnx"):
        own = extract_many({"g": gem("openvino-bf16")}, [image])["g"][0]
        plain = extract_many({"g": gem(None)}, [image])["g"][0]
    with cnn_runtime_as("openvino-bf16"):
        process = extract_many({"g": gem(None)}, [image])["g"][0]
    np.testing.assert_array_equal(own, process)
    assert not np.array_equal(own, plain)


def test_missing_openvino_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "openvino", None)  # import openvino -> ImportError
    with pytest.raises(MissingDependencyError, match=r"hmpf\[openvino\]"):
        ox.require_onnxruntime(export=False, runtime="openvino-bf16")
    ox.require_onnxruntime(export=False, runtime="onnx")  # the default needs no openvino


def test_precision_bf16_runs_a_methods_passes_in_openvino_bfloat16(cache_dir: Path) -> None:
    """``precision: bf16`` on one method: its passes run in OpenVINO at bfloat16 under the
    exported-model runtimes (the others' stay where they were), torch computes float32, and
    the method's keys change (``f32`` keeps the keys it had)."""
    ov = pytest.importorskip("openvino")
    size = list(SIZE)
    f32 = create_method("gem", {"input_size": size})
    bf16 = create_method("gem", {"input_size": size, "precision": "bf16"})
    assert (
        f32.cache_key()
        == create_method("gem", {"input_size": size, "precision": "f32"}).cache_key()
    )
    assert bf16.cache_key() != f32.cache_key() and bf16.group_key() != f32.group_key()
    image = np.random.default_rng(4).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    with cnn_runtime_as("onnx"):
        assert (f32.session_runtime(), bf16.session_runtime()) == ("onnx", "openvino-bf16")
        a = extract_many({"g": f32}, [image])["g"][0]
        b = extract_many({"g": bf16}, [image])["g"][0]
    sessions = {key[2]: maps.session for key, maps in ox._SESSIONS.items()}
    assert not isinstance(sessions["onnx"], ox.OpenVinoSession)
    compiled = sessions["openvino-bf16"].compiled
    if "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"):
        assert "bfloat16" in str(compiled.get_property("INFERENCE_PRECISION_HINT"))
    assert np.abs(a.astype(np.float32) - b.astype(np.float32)).max() <= BF16_ATOL
    with cnn_runtime_as("openvino"):
        assert bf16.session_runtime() == "openvino-bf16"
        assert f32.session_runtime() == "openvino"
    with cnn_runtime_as("torch"):
        assert bf16.session_runtime() == "torch"
    with pytest.raises(ConfigError):
        create_method("gem", {"precision": "fp8"})
