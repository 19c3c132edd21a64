"""HybridNet (Chen et al., ICRA 2017), the CaffeNet-style backbone of CNNHeat
(spec §2.1, docs/spec/hybridnet.md).

Weights: ``HybridNet.caffemodel`` (binary Caffe ``NetParameter``, V2 or legacy V1), read by
:mod:`hmpf.backbones.caffe_proto` without a caffe or protobuf dependency. Only conv1-conv5 are
loaded; conv6 and the fully connected layers are ignored.

Network (input 227 x 227 -> 55 -> 27 -> 13)::

    conv1 96x3x11x11 s4 -> relu1 -> pool1 max 3 s2 -> norm1 LRN(5, 1e-4, 0.75, k=1)
    conv2 256x48x5x5 p2 g2 -> relu2 -> pool2 max 3 s2 -> norm2 LRN(5, 1e-4, 0.75, k=1)
    conv3 384x256x3x3 p1 -> relu3 -> conv4 384x192x3x3 p1 g2 -> relu4
    conv5 256x192x3x3 p1 g2 -> relu5

Caffe's pooling rounds output sizes up (``ceil_mode=True``); Caffe's across-channel LRN
divides ``alpha`` by the window size exactly as ``torch.nn.LocalResponseNorm`` does, so the
torch module is used as is (checked against a numpy formula in the tests).

Exposed maps: ``relu4`` (384 channels), ``conv5`` (256, before the ReLU) and ``relu5`` (256,
13 x 13 at 227 x 227: MATLAB layer 15, what CNNHeat uses).

Options (``from_weights(path, device, **options)``):

* ``mean_mode="none"`` (default, HMPF-faithful): RGB 0-255 input, no mean subtraction. The
  caffemodel's conv1 expects BGR, so its input channels are flipped on loading; this is what
  MATLAB's ``importCaffeNetwork`` is believed to do **[U]** (spec §8.8).
* ``mean_mode="caffe"`` (Chen's recipe): BGR input minus the per-channel mean of
  ``amosnet_mean.npy`` (a (3, H, W) BGR mean image). ``mean_file`` names it; by default it is
  looked for next to the caffemodel (the release zip ships both).

Preprocessing in both modes: crop (§1.3), MATLAB ``imresize`` lanczos3 on uint8 (rounded), then
float32. Deviation: Chen's own script resizes with ``caffe.io`` (not lanczos3); only the mean
and channel order of his recipe are reproduced. The LRN/pooling hyper-parameters are the
published ones (§2.1), not read from the caffemodel's layer parameters.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import nn

from hmpf.backbones.base import MapsModuleBackbone, register_backbone, rgb3, weights_file
from hmpf.backbones.caffe_proto import ProtoError, parse_net
from hmpf.errors import ConfigError, WeightsError
from hmpf.imops import imresize, initcrop

__all__ = ["CONV_SHAPES", "CaffeNet", "HybridNetConvs"]

#: Caffe blob shapes (OIHW weight, bias) of the layers this backbone loads.
CONV_SHAPES: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "conv1": ((96, 3, 11, 11), (96,)),
    "conv2": ((256, 48, 5, 5), (256,)),
    "conv3": ((384, 256, 3, 3), (384,)),
    "conv4": ((384, 192, 3, 3), (384,)),
    "conv5": ((256, 192, 3, 3), (256,)),
}
_MEAN_MODES = ("none", "caffe")


class HybridNetConvs(nn.Module):
    """conv1-relu5 of HybridNet/CaffeNet; random weights until :func:`load_caffe_convs`."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 96, 11, stride=4)
        self.pool1 = nn.MaxPool2d(3, stride=2, ceil_mode=True)
        self.norm1 = nn.LocalResponseNorm(5, alpha=1e-4, beta=0.75, k=1.0)
        self.conv2 = nn.Conv2d(96, 256, 5, padding=2, groups=2)
        self.pool2 = nn.MaxPool2d(3, stride=2, ceil_mode=True)
        self.norm2 = nn.LocalResponseNorm(5, alpha=1e-4, beta=0.75, k=1.0)
        self.conv3 = nn.Conv2d(256, 384, 3, padding=1)
        self.conv4 = nn.Conv2d(384, 384, 3, padding=1, groups=2)
        self.conv5 = nn.Conv2d(384, 256, 3, padding=1, groups=2)

    def forward_maps(self, x: torch.Tensor, wanted: Collection[str]) -> dict[str, torch.Tensor]:
        """(B, 3, H, W) -> the requested maps among ``relu4``, ``conv5``, ``relu5``."""
        out: dict[str, torch.Tensor] = {}
        x = self.norm1(self.pool1(nnf.relu(self.conv1(x))))
        x = self.norm2(self.pool2(nnf.relu(self.conv2(x))))
        x = nnf.relu(self.conv4(nnf.relu(self.conv3(x))))
        if "relu4" in wanted:
            out["relu4"] = x
        if "conv5" in wanted or "relu5" in wanted:
            c5 = self.conv5(x)
            if "conv5" in wanted:
                out["conv5"] = c5
            if "relu5" in wanted:
                out["relu5"] = nnf.relu(c5)
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> relu5 (B, 256, h, w)."""
        return self.forward_maps(x, ("relu5",))["relu5"]


def read_caffe_convs(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """conv1-conv5 ``(weight OIHW, bias)`` float32 from a caffemodel, shapes checked.

    Raises:
        WeightsError: unreadable, truncated or corrupt file, a missing layer or a wrong shape.
    """
    try:
        data = path.read_bytes()
    except OSError as e:
        raise WeightsError(f"cannot read caffemodel {str(path)!r}: {e}") from e
    try:
        blobs = parse_net(data)
    except ProtoError as e:
        raise WeightsError(
            f"{str(path)!r} is not a readable Caffe caffemodel (truncated or corrupt?): {e}"
        ) from e
    out = {}
    for name, (wshape, bshape) in CONV_SHAPES.items():
        got = blobs.get(name)
        if not got or len(got) < 2:
            have = ", ".join(k for k, v in blobs.items() if v) or "none"
            raise WeightsError(
                f"{str(path)!r}: layer {name!r} with weight and bias blobs not found "
                f"(layers with blobs: {have}); is this HybridNet.caffemodel?"
            )
        arrs = []
        for arr, shape, what in ((got[0], wshape, "weight"), (got[1], bshape, "bias")):
            if arr.size != int(np.prod(shape)):
                raise WeightsError(
                    f"{str(path)!r}: layer {name!r} {what} has shape {arr.shape}, expected {shape}"
                )
            # Legacy files store 4-D shapes such as (1, 1, 1, 96) for a bias.
            arrs.append(np.array(arr.reshape(shape), dtype=np.float32))  # owns its data
        out[name] = (arrs[0], arrs[1])
    return out


def load_caffe_convs(
    module: HybridNetConvs, convs: Mapping[str, tuple[np.ndarray, np.ndarray]], rgb: bool
) -> None:
    """Copy ``convs`` into ``module``; ``rgb`` flips conv1's BGR input channels to RGB."""
    with torch.no_grad():
        for name, (w, b) in convs.items():
            if name == "conv1" and rgb:
                w = np.ascontiguousarray(w[:, ::-1])
            conv = getattr(module, name)
            conv.weight.copy_(torch.from_numpy(w))
            conv.bias.copy_(torch.from_numpy(b))


def _read_mean(path: Path) -> np.ndarray:
    """Per-channel BGR mean (3,) float32 of ``amosnet_mean.npy`` ((3, H, W) or (3,))."""
    p = weights_file(
        path,
        CaffeNet.name,
        "mean_mode 'caffe' needs amosnet_mean.npy from the HybridNet release zip "
        "(give its path as option mean_file).",
    )
    try:
        mean = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise WeightsError(f"cannot read mean file {str(p)!r}: {e}") from e
    mean = np.asarray(mean, dtype=np.float64)
    if mean.ndim == 3 and mean.shape[0] == 3:
        return mean.mean(axis=(1, 2)).astype(np.float32)
    if mean.shape == (3,):
        return mean.astype(np.float32)
    raise WeightsError(f"mean file {str(p)!r} has shape {mean.shape}, expected (3, H, W) BGR")


@register_backbone
class CaffeNet(MapsModuleBackbone):
    """HybridNet conv layers; see the module docstring for options and layers."""

    name = "caffenet"
    layers: ClassVar[dict[str, int]] = {"relu4": 384, "conv5": 256, "relu5": 256}
    default_input_size = (227, 227)
    weights_hint = (
        "Get HybridNet.caffemodel from the QUT/SPED download page linked by "
        "github.com/scutzetao/DLfeature_PlaceRecog_icra2017 and pass its path as weights."
    )

    def __init__(
        self,
        module: HybridNetConvs,
        device: str = "cpu",
        mean_mode: str = "none",
        mean_bgr: np.ndarray | None = None,
    ) -> None:
        super().__init__(module, device)
        self.mean_mode = mean_mode
        self.mean_bgr = mean_bgr

    @classmethod
    def from_weights(cls, path: Path | None, device: str = "cpu", **options: Any) -> CaffeNet:
        """Build conv1-relu5, then load ``path`` (a caffemodel).

        Options: ``mean_mode`` ("none" or "caffe"), ``mean_file`` (caffe mode only).
        """
        unknown = sorted(set(options) - {"mean_mode", "mean_file"})
        if unknown:
            raise ConfigError(
                f"backbone {cls.name!r}: unknown option(s) {unknown}; valid: mean_mode, mean_file"
            )
        mean_mode = options.get("mean_mode", "none")
        if mean_mode not in _MEAN_MODES:
            raise ConfigError(
                f"backbone {cls.name!r}: mean_mode must be one of {list(_MEAN_MODES)}, "
                f"got {mean_mode!r}"
            )
        if "mean_file" in options and mean_mode != "caffe":
            raise ConfigError(f"backbone {cls.name!r}: mean_file needs mean_mode 'caffe'")
        path = cls.weights_path(path)
        mean_bgr = None
        if mean_mode == "caffe":
            mean_bgr = _read_mean(Path(options.get("mean_file", path.parent / "amosnet_mean.npy")))
        module = HybridNetConvs()
        load_caffe_convs(module, read_caffe_convs(path), rgb=mean_mode == "none")
        return cls(module, device, mean_mode, mean_bgr)

    def preprocess(self, image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """H x W x 3 RGB uint8 -> 3 x rows x cols float32 (RGB 0-255, or BGR minus the mean)."""
        img = imresize(initcrop(rgb3(image)), size, "lanczos3").astype(np.float32)
        if self.mean_mode == "caffe":
            assert self.mean_bgr is not None
            img = img[:, :, ::-1] - self.mean_bgr
        return np.ascontiguousarray(img.transpose(2, 0, 1))
