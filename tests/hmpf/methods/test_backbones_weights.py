"""Weight loaders of the published CNNs, on synthetic files in the published layouts.

* HybridNet ``.caffemodel`` (V2 ``layer`` and legacy V1 ``layers``), written by our encoder.
* MatConvNet ``imagenet-vgg-m-1024.mat`` (beta17+ and older field names) and the NetVLAD
  ``Pitts30K_struct.mat``, written by ``scipy.io.savemat`` as cell arrays of structs so that
  ``loadmat(struct_as_record=False, squeeze_me=True)`` sees what it sees in the real files.

Weights are random (He scale) at the real conv shapes; fully connected layers and the WPCA
output are shrunk to keep the files small.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.io

from hmpf.backbones import load_backbone
from hmpf.backbones.caffe_proto import (
    ProtoError,
    encode_blob,
    encode_net,
    parse_blob,
    parse_layers,
    parse_net,
)
from hmpf.errors import ConfigError, WeightsError
from hmpf.imops import imresize, initcrop

torch = pytest.importorskip("torch")

from hmpf.backbones.caffenet import CONV_SHAPES, CaffeNet  # noqa: E402
from hmpf.backbones.vgg16 import VGG16_LAYERS, Vgg16NetVLAD  # noqa: E402
from hmpf.backbones.vgg_m import LayerSpec, VggM1024, _Conv, _lrn, _MaxPool  # noqa: E402

# ----------------------------------------------------------------------------- helpers


def _he(rng: np.random.Generator, shape: tuple[int, ...], fan_in: int) -> np.ndarray:
    return (rng.standard_normal(shape) * np.sqrt(2.0 / fan_in)).astype(np.float32)


def _cell(*items: Any) -> np.ndarray:
    """A MATLAB cell array (1 x n) of arbitrary items."""
    a = np.empty((1, len(items)), dtype=object)
    for i, x in enumerate(items):
        a[0, i] = x
    return a


def _image(seed: int, size: tuple[int, int] = (241, 321)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (*size, 3), dtype=np.uint8)


# HybridNet blobs: conv shapes are real, conv6 is real, fc7_new/fc8_new shrunk (real
# (4096, 9216) and (2543, 4096) would make a 170 MB file).
def _hybridnet_layers(rng: np.random.Generator) -> list[tuple[str, str, list[np.ndarray]]]:
    shapes = dict(CONV_SHAPES)
    shapes["conv6"] = ((256, 128, 3, 3), (256,))
    layers: list[tuple[str, str, list[np.ndarray]]] = [("data", "Input", [])]
    for name, (ws, bs) in shapes.items():
        w = _he(rng, ws, int(np.prod(ws[1:])))
        layers.append((name, "Convolution", [w, (0.1 * rng.standard_normal(bs)).astype("f4")]))
        layers.append(("relu" + name[4:], "ReLU", []))
    layers.append(("fc7_new", "InnerProduct", [_he(rng, (8, 32), 32), np.zeros(8, "f4")]))
    layers.append(("fc8_new", "InnerProduct", [_he(rng, (5, 8), 8), np.zeros(5, "f4")]))
    layers.append(("prob", "Softmax", []))
    return layers


def _write_caffemodel(path: Path, seed: int = 0, legacy: bool = False) -> list:
    layers = _hybridnet_layers(np.random.default_rng(seed))
    if legacy:  # V1 has no "Input" layer type
        layers = [x for x in layers if x[1] != "Input"]
    path.write_bytes(encode_net("HybridNet", layers, legacy=legacy))
    return layers


_VGGM_LRN = np.array([5.0, 2.0, 1e-3, 0.75])  # alpha larger than the real 1e-4: visible effect


def _vggm_layers(rng: np.random.Generator, old: bool) -> list[dict[str, Any]]:
    """The 21 SimpleNN layers of imagenet-vgg-m-1024 (fc layers shrunk)."""

    def conv(name: str, shape: tuple[int, ...], stride: int, pad: int) -> dict[str, Any]:
        w = _he(rng, shape, shape[0] * shape[1] * shape[2])
        b = (0.1 * rng.standard_normal(shape[3])).astype(np.float32)
        d: dict[str, Any] = {"name": name, "type": "conv"}
        if old:
            d |= {"filters": w, "biases": b.reshape(1, -1)}  # (1, cout)
        else:
            d["weights"] = _cell(w, b.reshape(-1, 1))  # (cout, 1)
        d |= {"stride": np.array([stride, stride], float), "pad": np.full(4, float(pad))}
        if not old:
            d["dilate"] = np.array([1.0, 1.0])
        return d

    def relu(name: str) -> dict[str, Any]:
        return {"name": name, "type": "relu", "leak": 0.0}

    def lrn(name: str) -> dict[str, Any]:
        return {"name": name, "type": "normalize" if old else "lrn", "param": _VGGM_LRN}

    def pool(name: str, pad: list[float]) -> dict[str, Any]:
        return {
            "name": name,
            "type": "pool",
            "method": "max",
            "pool": np.array([3.0, 3.0]),
            "stride": np.array([2.0, 2.0]),
            "pad": np.array(pad),
        }

    p = [0.0, 1.0, 0.0, 1.0]
    return [
        conv("conv1", (7, 7, 3, 96), 2, 0),
        relu("relu1"),
        lrn("norm1"),
        pool("pool1", p),
        conv("conv2", (5, 5, 96, 256), 2, 1),
        relu("relu2"),
        lrn("norm2"),
        pool("pool2", p),
        conv("conv3", (3, 3, 256, 512), 1, 1),
        relu("relu3"),
        conv("conv4", (3, 3, 512, 512), 1, 1),
        relu("relu4"),
        conv("conv5", (3, 3, 512, 512), 1, 1),
        relu("relu5"),
        pool("pool5", [0.0, 0.0, 0.0, 0.0]),
        conv("fc6", (1, 1, 512, 8), 1, 0),  # real (6, 6, 512, 4096): ignored by the loader
        relu("relu6"),
        conv("fc7", (1, 1, 8, 8), 1, 0),
        relu("relu7"),
        conv("fc8", (1, 1, 8, 10), 1, 0),
        {"name": "prob", "type": "softmax"},
    ]


def _write_vggm(
    path: Path, seed: int = 0, old: bool = False, wrapped: bool = False, full_mean: bool = True
) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    layers = _vggm_layers(rng, old)
    if full_mean:
        avg = (120 + 10 * rng.standard_normal((224, 224, 3))).astype(np.float32)
    else:
        avg = np.array([[[123.0, 117.0, 104.0]]], np.float32)
    norm = {
        "averageImage": avg,
        "imageSize": np.array([224.0, 224.0, 3.0]),
        "interpolation": "bilinear",
        "keepAspect": 1.0,
    }
    net: dict[str, Any] = {"layers": _cell(*layers)}
    if old:
        net |= {"normalization": norm, "classes": {"name": _cell("a", "b")}}
    else:
        net["meta"] = {"normalization": norm, "inputs": {"name": "input"}}
    # MATLAB's -v7 files are compressed: exercise that reader path too.
    scipy.io.savemat(path, {"net": net} if wrapped else net, do_compression=old)
    return layers


_VLAD_D, _VLAD_K, _WPCA_OUT = 512, 64, 16  # real WPCA output is 4096


def _pitts_layers(
    rng: np.random.Generator, convs: bool = True
) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """The 35 struct layers (VGG-16 real convs, real NetVLAD, small WPCA) and the head arrays.

    ``convs=False`` puts placeholder layers at 0-28 (for tests of the head checks, which run
    before the convs are read).
    """
    layers: list[dict[str, Any]] = []
    for name, kind, shape in VGG16_LAYERS:
        if not convs:
            layers.append({"name": name, "type": "relu"})
        elif kind == "conv":
            assert shape is not None
            w = _he(rng, shape, 9 * shape[2])
            b = (0.1 * rng.standard_normal(shape[3])).astype(np.float32)
            layers.append(
                {
                    "name": name,
                    "type": "conv",
                    "weights": _cell(w, b),
                    "pad": np.ones(4),
                    "stride": np.ones(2),
                }
            )
        elif kind == "relu":
            layers.append({"name": name, "type": "relu", "leak": 0.0})
        else:
            layers.append(
                {
                    "name": name,
                    "type": "pool",
                    "method": "max",
                    "pool": np.array([2.0, 2.0]),
                    "stride": np.array([2.0, 2.0]),
                    "pad": np.zeros(4),
                }
            )
    d, k = _VLAD_D, _VLAD_K
    head = {
        "assign": rng.standard_normal((1, 1, d, k)).astype(np.float32),
        "neg_centroids": rng.standard_normal((1, 1, d, k)).astype(np.float32),
        "wpca": (rng.standard_normal((1, 1, d * k, _WPCA_OUT)) * 0.01).astype(np.float32),
        "wpca_b": rng.standard_normal(_WPCA_OUT).astype(np.float32),
    }
    norm_param = np.array([2.0 * d, 1e-12, 1.0, 0.5])
    layers += [
        {"name": "preL2", "type": "normalize", "param": norm_param, "precious": 0.0},
        {
            "name": "vlad:core",
            "type": "custom",
            "K": float(k),
            "D": float(d),
            "vladDim": float(d * k),
            "weights": _cell(head["assign"], head["neg_centroids"]),
        },
        {"name": "vlad:intranorm", "type": "normalize", "param": norm_param},
        {"name": "postL2", "type": "custom"},
        {
            "name": "WPCA",
            "type": "conv",
            "weights": _cell(head["wpca"], head["wpca_b"]),
            "stride": 1.0,
            "pad": 0.0,
        },
        {"name": "finalL2", "type": "custom"},
    ]
    return layers, head


def _save_pitts(path: Path, layers: list[dict[str, Any]]) -> None:
    mean = np.array([[[123.68, 116.779, 103.939]]], np.float32)
    net = {"layers": _cell(*layers), "meta": {"normalization": {"averageImage": mean}}}
    scipy.io.savemat(path, {"net": net})


@pytest.fixture(scope="module")
def pitts(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    path = tmp_path_factory.mktemp("netvlad") / "Pitts30K_struct.mat"
    layers, head = _pitts_layers(np.random.default_rng(0))
    _save_pitts(path, layers)
    return path, head


def _caffe_lrn(x: np.ndarray, n: int, alpha: float, beta: float, k: float) -> np.ndarray:
    """Caffe ACROSS_CHANNELS LRN: x / (k + alpha/n * sum_{window} x^2)^beta, (C, H, W)."""
    c = x.shape[0]
    sq = np.zeros_like(x, dtype=np.float64)
    for i in range(c):
        lo, hi = max(0, i - (n - 1) // 2), min(c, i + n // 2 + 1)
        sq[i] = (x[lo:hi].astype(np.float64) ** 2).sum(0)
    return x / (k + alpha / n * sq) ** beta


def _matconvnet_lrn(x: np.ndarray, n: int, kappa: float, alpha: float, beta: float) -> np.ndarray:
    """vl_nnnormalize: x / (kappa + alpha * sum_{G(c)} x^2)^beta, alpha not divided by N."""
    c = x.shape[0]
    sq = np.zeros_like(x, dtype=np.float64)
    for i in range(c):
        lo, hi = max(0, i - (n - 1) // 2), min(c, i + n // 2 + 1)  # G(k), MatConvNet docs
        sq[i] = (x[lo:hi].astype(np.float64) ** 2).sum(0)
    return x / (kappa + alpha * sq) ** beta


# ----------------------------------------------------------------------------- caffe_proto


@pytest.mark.parametrize("legacy", [False, True])
def test_caffe_proto_roundtrip(legacy: bool) -> None:
    layers = _hybridnet_layers(np.random.default_rng(1))
    if legacy:
        layers = [x for x in layers if x[1] != "Input"]
    parsed = parse_layers(encode_net("HybridNet", layers, legacy=legacy))
    assert [(p.name, p.type) for p in parsed] == [(n, t) for n, t, _ in layers]
    blobs = parse_net(encode_net("HybridNet", layers, legacy=legacy))
    assert list(blobs) == [n for n, _, _ in layers]
    for name, _, arrs in layers:
        assert len(blobs[name]) == len(arrs)
        for got, want in zip(blobs[name], arrs, strict=True):
            assert got.dtype == np.float32
            if legacy:  # num/channels/height/width: left-padded to 4-D
                assert got.shape == (1,) * (4 - want.ndim) + want.shape
            else:
                assert got.shape == want.shape
            np.testing.assert_array_equal(got.reshape(want.shape), want)
    assert blobs["conv1"][0].shape == (96, 3, 11, 11)
    assert blobs["conv2"][0].shape == (256, 48, 5, 5)
    assert blobs["conv5"][0].shape == (256, 192, 3, 3)


def test_caffe_proto_unpacked_double_and_unknown_fields() -> None:
    a = np.arange(6, dtype=np.float32).reshape(2, 3) - 2.5
    for packed in (True, False):
        for double in (True, False):
            got = parse_blob(encode_blob(a, packed=packed, double=double))
            assert got.dtype == (np.float64 if double else np.float32)
            np.testing.assert_array_equal(got, a)
    # Unpacked BlobShape dims and legacy dims.
    shape_unpacked = bytes([0x3A, 0x04, 0x08, 0x02, 0x08, 0x03])  # shape{dim:2 dim:3}
    data = bytes([0x2A, 24]) + a.tobytes()  # packed data = 5
    np.testing.assert_array_equal(parse_blob(shape_unpacked + data), a)
    legacy = parse_blob(encode_blob(a, legacy_shape=True))
    assert legacy.shape == (1, 1, 2, 3)
    # A V2 layer with fields the reader does not use (varint, 64-bit and 32-bit wire types;
    # the field numbers only matter to the parser through their wire type) is still read.
    body = bytes([0x0A, 0x01]) + b"c"  # name = "c"
    body += bytes([0x12, 0x0B]) + b"Convolution"  # type
    body += bytes([0x18, 0x96, 0x01])  # field 3, varint 150
    body += bytes([0x21]) + bytes(8)  # field 4, 64-bit
    body += bytes([0x2D]) + bytes(4)  # field 5, 32-bit
    blob = encode_blob(a)
    body += bytes([0x3A, len(blob)]) + blob  # blobs = 7
    net = bytes([0x0A, 0x01]) + b"n" + bytes([0xA2, 0x06, len(body)]) + body  # layer = 100
    (layer,) = parse_layers(net)
    assert (layer.name, layer.type) == ("c", "Convolution")
    np.testing.assert_array_equal(layer.blobs[0], a)


def test_caffe_proto_rejects_corrupt_bytes() -> None:
    good = encode_net("n", [("c", "Convolution", [np.ones((4, 4), np.float32)])])
    with pytest.raises(ProtoError):
        parse_net(good[: len(good) - 7])  # truncated inside the blob
    with pytest.raises(ProtoError):
        parse_net(b"\xff" * 40)  # endless varint
    with pytest.raises(ProtoError):
        parse_net(bytes([0x0B, 0x00]))  # wire type 3 (group)
    with pytest.raises(ProtoError):
        parse_net(encode_net("n", []))  # no layers
    # BlobShape says 6 values, data holds 5.
    five = np.ones(5, np.float32).tobytes()
    with pytest.raises(ProtoError, match="holds 5 values"):
        parse_blob(b"\x3a\x02\x08\x06" + b"\x2a\x14" + five)


# ----------------------------------------------------------------------------- caffenet


@pytest.mark.parametrize("legacy", [False, True])
def test_caffenet_maps(tmp_path: Path, legacy: bool) -> None:
    path = tmp_path / "HybridNet.caffemodel"
    _write_caffemodel(path, seed=2, legacy=legacy)
    net = load_backbone("caffenet", weights=str(path))
    assert isinstance(net, CaffeNet) and net.mean_mode == "none"
    x = torch.from_numpy(net.preprocess(_image(3), net.default_input_size))[None]
    assert x.shape == (1, 3, 227, 227)
    maps = net.forward_maps(x, ["relu4", "conv5", "relu5"])
    assert maps["relu4"].shape == (1, 384, 13, 13)
    assert maps["conv5"].shape == (1, 256, 13, 13)
    assert maps["relu5"].shape == (1, 256, 13, 13)
    assert (maps["conv5"] < 0).any()
    torch.testing.assert_close(maps["relu5"], torch.relu(maps["conv5"]))
    assert set(net.forward_maps(x, ["relu5"])) == {"relu5"}
    with pytest.raises(ValueError, match="no layer"):
        net.forward_maps(x, ["fc7_new"])


def test_caffenet_rgb_input_matches_bgr_weights(tmp_path: Path) -> None:
    """mean_mode none: conv1 on RGB input == the file's BGR conv1 on the BGR image."""
    path = tmp_path / "HybridNet.caffemodel"
    layers = dict((n, b) for n, _, b in _write_caffemodel(path, seed=4))
    w, b = layers["conv1"]
    net = CaffeNet.from_weights(path)
    img = _image(5)
    x = net.preprocess(img, (227, 227))
    expect = imresize(initcrop(img), (227, 227), "lanczos3").astype(np.float32)
    np.testing.assert_array_equal(x, expect.transpose(2, 0, 1))  # RGB, 0..255, no mean
    with torch.no_grad():
        y = net.module.conv1(torch.from_numpy(x)[None])[0].numpy()
    bgr = x[::-1]
    for o, r, c in [(0, 0, 0), (17, 30, 41), (95, 54, 54)]:
        ref = float((w[o] * bgr[:, 4 * r : 4 * r + 11, 4 * c : 4 * c + 11]).sum() + b[o])
        assert y[o, r, c] == pytest.approx(ref, rel=1e-4, abs=1e-3)
    # The flip matters: the same weights unflipped give another answer on a colour image.
    rgb_ref = float((w[17] * x[:, 120:131, 164:175]).sum() + b[17])
    assert abs(y[17, 30, 41] - rgb_ref) > 1e-2


def test_caffenet_caffe_mean_mode(tmp_path: Path) -> None:
    path = tmp_path / "HybridNet.caffemodel"
    layers = dict((n, b) for n, _, b in _write_caffemodel(path, seed=6))
    mean_img = np.random.default_rng(0).uniform(90, 130, (3, 256, 256)).astype(np.float32)
    np.save(tmp_path / "amosnet_mean.npy", mean_img)
    net = load_backbone("caffenet", weights=str(path), options={"mean_mode": "caffe"})
    img = _image(7)
    x = net.preprocess(img, (227, 227))
    rgb = imresize(initcrop(img), (227, 227), "lanczos3").astype(np.float32)
    expect = rgb[:, :, ::-1] - mean_img.mean(axis=(1, 2))  # BGR minus the per-channel mean
    np.testing.assert_allclose(x, expect.transpose(2, 0, 1), rtol=0, atol=1e-4)
    # Weights stay BGR-ordered.
    np.testing.assert_array_equal(net.module.conv1.weight.detach().numpy(), layers["conv1"][0])
    other = tmp_path / "elsewhere.npy"
    np.save(other, np.full((3, 4, 4), 7.0, np.float32))
    net2 = CaffeNet.from_weights(path, mean_mode="caffe", mean_file=str(other))
    np.testing.assert_allclose(net2.mean_bgr, [7.0, 7.0, 7.0])


def test_caffenet_options_and_mean_errors(tmp_path: Path) -> None:
    path = tmp_path / "HybridNet.caffemodel"
    _write_caffemodel(path, seed=8)
    with pytest.raises(ConfigError, match="unknown option"):
        load_backbone("caffenet", weights=str(path), options={"mean": "caffe"})
    with pytest.raises(ConfigError, match="mean_mode"):
        CaffeNet.from_weights(path, mean_mode="imagenet")
    with pytest.raises(ConfigError, match="mean_file"):
        CaffeNet.from_weights(path, mean_file="x.npy")
    with pytest.raises(WeightsError, match="amosnet_mean.npy"):
        CaffeNet.from_weights(path, mean_mode="caffe")  # not next to the caffemodel
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((4, 2, 2)))
    with pytest.raises(WeightsError, match="bad.npy"):
        CaffeNet.from_weights(path, mean_mode="caffe", mean_file=str(bad))


def test_caffe_lrn_and_ceil_pooling() -> None:
    """torch LocalResponseNorm(5, 1e-4, 0.75, 1) is Caffe's LRN; pools round up."""
    from hmpf.backbones.caffenet import HybridNetConvs

    m = HybridNetConvs()
    x = np.random.default_rng(9).uniform(0, 400, (12, 7, 6)).astype(np.float32)
    with torch.no_grad():
        y = m.norm1(torch.from_numpy(x)[None])[0].numpy()
    want = _caffe_lrn(x, 5, 1e-4, 0.75, 1.0)
    assert np.abs(want - x).max() > 1.0  # the normalisation is not negligible here
    np.testing.assert_allclose(y, want, rtol=1e-5)
    with torch.no_grad():
        assert m.pool1(torch.zeros(1, 96, 56, 56)).shape[-2:] == (28, 28)  # floor mode: 27
        assert m(torch.zeros(1, 3, 227, 227)).shape == (1, 256, 13, 13)


def test_caffenet_wrong_layout(tmp_path: Path) -> None:
    rng = np.random.default_rng(10)
    layers = [x for x in _hybridnet_layers(rng) if x[0] != "conv5"]
    path = tmp_path / "no_conv5.caffemodel"
    path.write_bytes(encode_net("x", layers))
    with pytest.raises(WeightsError, match="no_conv5.caffemodel.*'conv5'"):
        CaffeNet.from_weights(path)
    layers = _hybridnet_layers(rng)
    layers = [
        (n, t, [np.zeros((256, 96, 5, 5), np.float32), b[1]] if n == "conv2" else b)
        for n, t, b in layers
    ]
    path = tmp_path / "ungrouped.caffemodel"
    path.write_bytes(encode_net("x", layers))
    with pytest.raises(WeightsError, match=r"'conv2' weight has shape \(256, 96, 5, 5\)"):
        CaffeNet.from_weights(path)


# ----------------------------------------------------------------------------- vgg_m_1024


@pytest.mark.parametrize(("old", "wrapped"), [(False, False), (True, False), (False, True)])
def test_vggm_maps(tmp_path: Path, old: bool, wrapped: bool) -> None:
    path = tmp_path / "imagenet-vgg-m-1024.mat"
    layers = _write_vggm(path, seed=11, old=old, wrapped=wrapped)
    net = load_backbone("vgg_m_1024", weights=str(path))
    assert isinstance(net, VggM1024) and net.image_size == (224, 224)
    x = torch.from_numpy(net.preprocess(_image(12), (224, 224)))[None]
    maps = net.forward_maps(x, ["conv4", "relu4", "relu5"])
    for k in ("conv4", "relu4", "relu5"):
        assert maps[k].shape == (1, 512, 13, 13)
    torch.testing.assert_close(maps["relu4"], torch.relu(maps["conv4"]))
    # conv1 is MatConvNet's cross-correlation of W (h, w, cin, cout) at stride 2, no pad.
    w = layers[0]["filters"] if old else layers[0]["weights"][0, 0]
    b = (layers[0]["biases"] if old else layers[0]["weights"][0, 1]).ravel()
    with torch.no_grad():
        y = net.module.chain[0](x)[0].numpy()
    assert y.shape == (96, 109, 109)
    xi = x[0].numpy()
    for o, r, c in [(0, 0, 0), (50, 33, 71), (95, 108, 108)]:
        patch = xi[:, 2 * r : 2 * r + 7, 2 * c : 2 * c + 7]  # (cin, 7, 7)
        ref = float(np.einsum("chw,hwc->", patch, w[:, :, :, o]) + b[o])
        assert y[o, r, c] == pytest.approx(ref, rel=1e-4, abs=1e-3)


def test_vggm_lrn_is_matconvnet_normalize() -> None:
    n, kappa, alpha, beta = 5, 2.0, 1e-3, 0.75
    lrn = _lrn(LayerSpec("norm1", "lrn", lrn=(n, kappa, alpha, beta)))
    x = np.random.default_rng(13).uniform(-60, 60, (9, 4, 5)).astype(np.float32)
    with torch.no_grad():
        y = lrn(torch.from_numpy(x)[None])[0].numpy()
    want = _matconvnet_lrn(x, n, kappa, alpha, beta)
    assert np.abs(want - x / kappa**beta).max() > 0.1  # the sum term matters
    np.testing.assert_allclose(y, want, rtol=1e-5)


def test_vggm_asymmetric_pool_and_conv_padding() -> None:
    pool = _MaxPool(LayerSpec("pool2", "pool", pool=(3, 3), stride=(2, 2), pad=(0, 1, 0, 1)))
    x = -1.0 - torch.rand(1, 2, 26, 26)  # all negative: zero padding would show up as 0
    y = pool(x)
    assert y.shape == (1, 2, 13, 13)
    assert pool(torch.zeros(1, 1, 109, 109)).shape[-2:] == (54, 54)
    xn = x[0].numpy()
    # Last window: rows/cols 24, 25 and the -inf pad.
    np.testing.assert_allclose(y[0, :, 12, 12].numpy(), xn[:, 24:26, 24:26].max(axis=(1, 2)))
    np.testing.assert_allclose(y[0, :, 0, 0].numpy(), xn[:, 0:3, 0:3].max(axis=(1, 2)))
    assert (y < 0).all()

    w = np.random.default_rng(14).standard_normal((3, 3, 2, 4)).astype(np.float32)
    spec = LayerSpec("c", "conv", weight=w, bias=np.zeros(4, np.float32), pad=(0, 1, 2, 0))
    conv = _Conv(spec)
    with torch.no_grad():
        conv.conv.weight.copy_(torch.from_numpy(w.transpose(3, 2, 0, 1).copy()))
        conv.conv.bias.zero_()
        z = conv(torch.ones(1, 2, 8, 8))
    assert z.shape == (1, 4, 8 + 1 - 2, 8 + 2 - 2)
    # Top-left output: its window covers two zero-padded columns on the left.
    assert float(z[0, 0, 0, 0]) == pytest.approx(float(w[:, 2:, :, 0].sum()), rel=1e-5)


def test_vggm_preprocess(tmp_path: Path) -> None:
    path = tmp_path / "vggm.mat"
    _write_vggm(path, seed=15, full_mean=True)
    net = VggM1024.from_weights(path)
    img = _image(16)
    x = net.preprocess(img, (224, 224))
    resized = imresize(initcrop(img).astype(np.float64), (224, 224), "lanczos3")
    assert np.any(np.abs(resized - np.round(resized)) > 1e-3)  # float resize, not rounded
    expect = (resized - net.average_image).transpose(2, 0, 1)
    np.testing.assert_allclose(x, expect, rtol=0, atol=1e-3)
    # Another input size: the full mean image is resized with it.
    x2 = net.preprocess(img, (112, 160))
    mean2 = imresize(net.average_image, (112, 160), "lanczos3")
    expect2 = imresize(initcrop(img).astype(np.float64), (112, 160), "lanczos3") - mean2
    np.testing.assert_allclose(x2, expect2.transpose(2, 0, 1), rtol=0, atol=1e-3)
    # A (1, 1, 3) mean broadcasts.
    path2 = tmp_path / "vggm_pixel_mean.mat"
    _write_vggm(path2, seed=15, full_mean=False)
    net2 = VggM1024.from_weights(path2)
    x3 = net2.preprocess(img, (224, 224))
    np.testing.assert_allclose(x3, (resized - [123, 117, 104]).transpose(2, 0, 1), atol=1e-3)


def test_vggm_wrong_layout(tmp_path: Path) -> None:
    rng = np.random.default_rng(17)
    layers = _vggm_layers(rng, old=False)
    layers[8]["weights"] = _cell(np.zeros((3, 3, 256, 384), np.float32), np.zeros(384, "f4"))
    path = tmp_path / "bad_conv3.mat"
    scipy.io.savemat(path, {"layers": _cell(*layers)})
    with pytest.raises(WeightsError, match=r"bad_conv3.mat.*layer 8 \('conv3'"):
        VggM1024.from_weights(path)
    layers = _vggm_layers(rng, old=False)
    layers[2]["type"] = "bnorm"
    path = tmp_path / "bad_type.mat"
    scipy.io.savemat(path, {"layers": _cell(*layers)})
    with pytest.raises(WeightsError, match="'norm1'.*'bnorm'"):
        VggM1024.from_weights(path)
    path = tmp_path / "not_simplenn.mat"
    scipy.io.savemat(path, {"x": np.zeros(3)})
    with pytest.raises(WeightsError, match="not a MatConvNet SimpleNN"):
        VggM1024.from_weights(path)
    with pytest.raises(ConfigError):
        load_backbone("vgg_m_1024", weights=str(path), options={"mean_mode": "none"})


# ----------------------------------------------------------------------------- vgg16


def test_vgg16_maps_and_netvlad_params(pitts: tuple[Path, dict[str, np.ndarray]]) -> None:
    path, stored = pitts
    net = load_backbone("vgg16", weights=str(path))
    assert isinstance(net, Vgg16NetVLAD)
    img = _image(18)
    x = net.preprocess(img, (224, 224))
    resized = imresize(initcrop(img), (224, 224), "lanczos3").astype(np.float32)
    mean = np.array([123.68, 116.779, 103.939], np.float32)
    np.testing.assert_allclose(x, (resized - mean).transpose(2, 0, 1), atol=1e-4)
    maps = net.forward_maps(torch.from_numpy(x)[None], ["conv5_3"])
    assert maps["conv5_3"].shape == (1, 512, 14, 14)
    assert (maps["conv5_3"] < 0).any()  # no ReLU after conv5_3

    p = net.netvlad_params()
    assert set(p) == {"assign", "centroids", "wpca_w", "wpca_b"}
    d, k = _VLAD_D, _VLAD_K
    assert p["assign"].shape == (d, k) and p["centroids"].shape == (k, d)
    assert p["wpca_w"].shape == (d * k, _WPCA_OUT) and p["wpca_b"].shape == (_WPCA_OUT,)
    assert all(v.dtype == np.float32 for v in p.values())
    np.testing.assert_array_equal(p["assign"], stored["assign"][0, 0])
    np.testing.assert_array_equal(p["centroids"], -stored["neg_centroids"][0, 0].T)
    np.testing.assert_array_equal(p["wpca_w"], stored["wpca"][0, 0])
    np.testing.assert_array_equal(p["wpca_b"], stored["wpca_b"])

    # The head runs on these parameters (spec §2.5, docs/spec/netvlad.md): unit-norm output.
    f = maps["conv5_3"][0].reshape(512, -1).numpy().T.astype(np.float64)  # (N, D)
    f /= np.sqrt(1e-12 + (f**2).sum(1, keepdims=True))
    s = f @ p["assign"]
    a = np.exp(s - s.max(1, keepdims=True))
    a /= a.sum(1, keepdims=True)
    v = a.T @ f - a.sum(0)[:, None] * p["centroids"]  # (K, D)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v.T.ravel()  # (D, K) C order: k fastest
    v /= np.linalg.norm(v)
    y = v @ p["wpca_w"] + p["wpca_b"]
    assert np.linalg.norm(y / np.linalg.norm(y)) == pytest.approx(1.0)


def test_vgg16_head_layout_errors(tmp_path: Path) -> None:
    rng = np.random.default_rng(19)
    layers, _ = _pitts_layers(rng, convs=False)
    layers[30]["weights"] = _cell(rng.standard_normal((1, 1, 256, 64)).astype("f4"), np.zeros(3))
    path = tmp_path / "bad_vlad.mat"
    _save_pitts(path, layers)
    with pytest.raises(WeightsError, match=r"bad_vlad.mat.*layer 30 \('vlad:core'\)"):
        Vgg16NetVLAD.from_weights(path)

    layers, _ = _pitts_layers(rng, convs=False)
    layers[33]["weights"] = _cell(np.zeros((1, 1, 1000, 16), "f4"), np.zeros(16, "f4"))
    path = tmp_path / "bad_wpca.mat"
    _save_pitts(path, layers)
    with pytest.raises(WeightsError, match=r"bad_wpca.mat.*layer 33 \('WPCA'\)"):
        Vgg16NetVLAD.from_weights(path)

    layers, _ = _pitts_layers(rng, convs=False)
    layers[31] = {"name": "vlad:core2", "type": "custom"}
    path = tmp_path / "bad_names.mat"
    _save_pitts(path, layers)
    with pytest.raises(WeightsError, match="layer 31 is 'vlad:core2'"):
        Vgg16NetVLAD.from_weights(path)

    layers, _ = _pitts_layers(rng, convs=False)
    path = tmp_path / "short.mat"
    _save_pitts(path, layers[:33])
    with pytest.raises(WeightsError, match="short.mat.*expected 35"):
        Vgg16NetVLAD.from_weights(path)

    layers, _ = _pitts_layers(rng, convs=False)  # the head is fine, the convs are not
    path = tmp_path / "no_convs.mat"
    _save_pitts(path, layers)
    with pytest.raises(WeightsError, match=r"layer 0 \('conv1_1'.*type 'relu'"):
        Vgg16NetVLAD.from_weights(path)
    with pytest.raises(ConfigError):
        Vgg16NetVLAD.from_weights(path, whiten=False)


# ----------------------------------------------------------------------------- common errors

_FILES = {
    "caffenet": ("HybridNet.caffemodel", "DLfeature_PlaceRecog_icra2017"),
    "vgg_m_1024": ("imagenet-vgg-m-1024.mat", "vlfeat.org/matconvnet/pretrained"),
    "vgg16": ("Pitts30K_struct.mat", "Hierarchical-Localization"),
}


@pytest.mark.parametrize("name", sorted(_FILES))
def test_missing_weights_name_file_and_hint(tmp_path: Path, name: str) -> None:
    fname, hint = _FILES[name]
    with pytest.raises(WeightsError, match=fname) as err:
        load_backbone(name, weights=str(tmp_path / fname))
    assert hint in str(err.value)
    from hmpf.backbones.base import _registry

    with pytest.raises(WeightsError, match="needs a weight file"):
        _registry()[name].from_weights(None)


@pytest.mark.parametrize("name", sorted(_FILES))
def test_corrupt_and_truncated_weights(tmp_path: Path, name: str) -> None:
    fname = _FILES[name][0]
    path = tmp_path / fname
    if name == "caffenet":
        _write_caffemodel(path)
    elif name == "vgg_m_1024":
        _write_vggm(path, old=True)  # compressed
    else:
        _save_pitts(path, _pitts_layers(np.random.default_rng(0), convs=False)[0])
    data = path.read_bytes()
    cut = tmp_path / ("cut_" + fname)
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(WeightsError, match="cut_"):
        load_backbone(name, weights=str(cut))
    junk = tmp_path / ("junk_" + fname)
    junk.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(WeightsError, match="junk_"):
        load_backbone(name, weights=str(junk))
