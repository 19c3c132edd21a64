"""VGG-M-1024 (Chatfield et al.), the backbone of Only Look Once (spec §2.4, §3.2:
docs/spec/olo.md, docs/spec/weights.md).

Weights: MatConvNet SimpleNN ``imagenet-vgg-m-1024.mat`` read with
``scipy.io.loadmat(struct_as_record=False, squeeze_me=True)``. Both layouts are accepted:

* beta17+ ("tidy"): ``weights = {W, b}``, LRN type ``lrn``, ``meta.normalization``;
* older: ``filters`` / ``biases``, LRN type ``normalize``, top-level ``normalization``.

The variables may sit at the top level of the file (``save -struct net``; Python readers of the
MatConvNet model files use ``mat["layers"]``) or inside a ``net`` struct. Only conv1-relu5 are
read; pool5 and fc6-fc8 are ignored.

Network (224 x 224 -> 109 -> 54 -> 26 -> 13), hyper-parameters taken from the file::

    conv1 96x7x7x3 s2 -> relu1 -> norm1 -> pool1 max 3 s2 pad [0 1 0 1]
    conv2 256x5x5x96 s2 p1 -> relu2 -> norm2 -> pool2 max 3 s2 pad [0 1 0 1]
    conv3 512x3x3 p1 -> relu3 -> conv4 512x3x3 p1 -> relu4 -> conv5 512x3x3 p1 -> relu5

Conversions: ``W`` (h, w, cin, cout) -> OIHW by ``transpose(3, 2, 0, 1)`` (MatConvNet
cross-correlates like torch). MatConvNet pads are ``[top bottom left right]``: asymmetric conv
padding is applied with ``nnf.pad`` (zeros), pool padding with ``-inf`` then a plain max pool,
which reproduces ``vl_nnpool`` (26 -> 13 for pool2). MatConvNet LRN ``param = [N kappa alpha
beta]`` is ``x / (kappa + alpha * sum_N x^2)^beta`` with alpha *not* divided by N, so it maps to
``torch.nn.LocalResponseNorm(N, alpha * N, beta, kappa)``; this is exact for odd N (both
centre the window the same way) and an even N is refused.

Exposed maps: ``conv4``, ``relu4`` (OLO's features, ``res(13)``), ``conv5`` and ``relu5``
(OLO's masks, ``res(15)``), each 512 x 13 x 13 at 224 x 224.

Preprocessing (HMPF): crop (§1.3), float (0-255, no rounding), MATLAB ``imresize`` lanczos3 to
the requested size (224 x 224 = ``meta.normalization.imageSize``; the file's value is kept as
``image_size``), minus ``averageImage``, RGB. The mean may be (1, 1, 3), (3,) or a full
H x W x 3 image (which one the real file holds is not verified **[U]**); a full image is resized
with lanczos3 when the input size differs from it (MATLAB would fail there instead).
Deviation: MATLAB computes in single precision, this port in float64 until the final float32
cast.

The SimpleNN readers (:func:`load_mat`, :func:`simplenn`, :func:`parse_chain`) and the torch
chain (:class:`SimpleNN`) are shared with :mod:`hmpf.backbones.vgg16`.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import nn

from hmpf.backbones.base import MapsModuleBackbone, register_backbone, rgb3
from hmpf.errors import WeightsError
from hmpf.imops import imresize, initcrop

__all__ = [
    "LayerSpec",
    "SimpleNN",
    "VggM1024",
    "load_mat",
    "parse_chain",
    "simplenn",
]


# ----------------------------------------------------------------------------- .mat reading


def load_mat(path: Path) -> dict[str, Any]:
    """``loadmat(path, struct_as_record=False, squeeze_me=True)``; failures -> WeightsError."""
    import scipy.io  # scipy takes ~0.6 s to import: loaded on first use

    try:
        return scipy.io.loadmat(str(path), struct_as_record=False, squeeze_me=True)
    except NotImplementedError as e:  # scipy's answer to MAT v7.3 (HDF5)
        raise WeightsError(
            f"{str(path)!r} is a MATLAB v7.3 (HDF5) file, which scipy cannot read; "
            f"re-save it with save(..., '-v7'): {e}"
        ) from e
    except Exception as e:  # scipy raises many types on truncated or corrupt files
        raise WeightsError(
            f"cannot read {str(path)!r} as a MATLAB .mat file (truncated or corrupt?): "
            f"{type(e).__name__}: {e}"
        ) from e


def _items(v: Any) -> list[Any]:
    """A MATLAB cell/struct array (squeezed to an object array or a scalar) as a list."""
    if isinstance(v, np.ndarray):
        return list(v.ravel())
    return [v]


def simplenn(mat: dict[str, Any], path: Path) -> tuple[list[Any], Any]:
    """``(layers, normalization struct or None)`` of a SimpleNN file, either top-level layout.

    Accepts variables ``layers`` + ``meta``/``normalization`` at the top level, or a ``net``
    struct holding them.
    """
    holder: Any = mat.get("net")
    if holder is not None and hasattr(holder, "layers"):

        def get(k: str) -> Any:
            return getattr(holder, k, None)

    elif "layers" in mat:

        def get(k: str) -> Any:
            return mat.get(k)

    else:
        found = sorted(k for k in mat if not k.startswith("__"))
        raise WeightsError(
            f"{str(path)!r} is not a MatConvNet SimpleNN file: no 'layers' or 'net.layers' "
            f"(variables: {found})"
        )
    meta = get("meta")
    norm = getattr(meta, "normalization", None) if meta is not None else None
    if norm is None:
        norm = get("normalization")
    return _items(get("layers")), norm


def _field(layer: Any, name: str, default: Any = None) -> Any:
    return getattr(layer, name, default)


def _ints(v: Any, n_ok: Sequence[int], what: str) -> tuple[int, ...]:
    a = np.atleast_1d(np.asarray(v, dtype=np.float64)).ravel()
    if a.size not in n_ok or np.any(a != np.round(a)) or np.any(a < 0):
        raise ValueError(f"{what} = {a.tolist()}")
    return tuple(int(x) for x in a)


def _pair(v: Any, what: str, default: int) -> tuple[int, int]:
    if v is None:
        return default, default
    a = _ints(v, (1, 2), what)
    return (a[0], a[0]) if len(a) == 1 else (a[0], a[1])


def _pad4(v: Any) -> tuple[int, int, int, int]:
    """MatConvNet ``pad``: scalar or ``[top bottom left right]``."""
    if v is None:
        return 0, 0, 0, 0
    a = _ints(v, (1, 4), "pad")
    return (a[0],) * 4 if len(a) == 1 else (a[0], a[1], a[2], a[3])


@dataclass
class LayerSpec:
    """One SimpleNN layer: canonical name, kind and hyper-parameters (arrays for convs).

    ``weight`` is MatConvNet (h, w, cin, cout) float32, ``bias`` (cout,) float32; ``stride`` and
    ``pool`` are (y, x); ``pad`` is (top, bottom, left, right); ``lrn`` is (N, kappa, alpha,
    beta); ``leak`` is the ReLU slope for negatives.
    """

    name: str
    kind: str  # conv | relu | lrn | pool
    weight: np.ndarray | None = None
    bias: np.ndarray | None = None
    stride: tuple[int, int] = (1, 1)
    pad: tuple[int, int, int, int] = (0, 0, 0, 0)
    pool: tuple[int, int] = (1, 1)
    lrn: tuple[int, float, float, float] = (5, 1.0, 1e-4, 0.75)
    leak: float = 0.0


_KIND_TYPES = {"conv": {"conv"}, "relu": {"relu"}, "lrn": {"lrn", "normalize"}, "pool": {"pool"}}


def _conv_arrays(layer: Any, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    ws = _field(layer, "weights")
    if ws is not None and np.size(ws) > 0:
        items = _items(ws) if isinstance(ws, np.ndarray) and ws.dtype == object else [ws]
        w = items[0]
        b = items[1] if len(items) > 1 else None
    else:  # pre-beta17 field names
        w, b = _field(layer, "filters"), _field(layer, "biases")
    if w is None:
        raise ValueError("no weights (neither 'weights' nor 'filters')")
    w = np.asarray(w, dtype=np.float32)
    cout = shape[3]
    if w.ndim != 4 and w.size == math.prod(shape):
        w = w.reshape(shape)  # squeeze_me removed unit dimensions (1 x 1 kernels)
    if w.shape != shape:
        raise ValueError(f"weight shape {w.shape}, expected {shape} (h, w, cin, cout)")
    if b is None or np.size(b) == 0:
        bias = np.zeros(cout, np.float32)
    else:
        bias = np.asarray(b, dtype=np.float32).ravel()  # (cout,), (1, cout) or (cout, 1)
        if bias.size != cout:
            raise ValueError(f"bias of {bias.size} values, expected {cout}")
    return w, bias


def parse_chain(
    path: Path,
    layers: Sequence[Any],
    expected: Sequence[tuple[str, str, tuple[int, ...] | None]],
) -> list[LayerSpec]:
    """Check ``layers[:len(expected)]`` against ``(name, kind, W shape)`` and read them.

    Raises:
        WeightsError: naming the file and the layer, on a missing layer, a wrong type or shape,
            or an unsupported setting.
    """
    if len(layers) < len(expected):
        raise WeightsError(
            f"{str(path)!r}: {len(layers)} layers, expected at least {len(expected)} "
            f"(up to {expected[-1][0]})"
        )
    specs = []
    for i, (name, kind, shape) in enumerate(expected):
        layer = layers[i]
        fname = str(_field(layer, "name", name))
        ltype = str(_field(layer, "type", ""))
        where = f"{str(path)!r}: layer {i} ({fname!r}, expected {name!r})"
        if ltype not in _KIND_TYPES[kind]:
            raise WeightsError(f"{where} has type {ltype!r}, expected {kind!r}")
        try:
            if kind == "conv":
                assert shape is not None
                w, b = _conv_arrays(layer, shape)
                dil = _field(layer, "dilate")
                if dil is not None and _pair(dil, "dilate", 1) != (1, 1):
                    raise ValueError(f"dilate = {np.ravel(dil).tolist()} is not supported")
                spec = LayerSpec(
                    name,
                    kind,
                    weight=w,
                    bias=b,
                    stride=_pair(_field(layer, "stride"), "stride", 1),
                    pad=_pad4(_field(layer, "pad")),
                )
            elif kind == "relu":
                leak = _field(layer, "leak")
                spec = LayerSpec(name, kind, leak=float(leak) if np.size(leak) == 1 else 0.0)
            elif kind == "lrn":
                p = np.asarray(_field(layer, "param"), dtype=np.float64).ravel()
                if p.size != 4 or p[0] != round(p[0]) or int(p[0]) % 2 == 0:
                    raise ValueError(f"param = {p.tolist()}: need [N kappa alpha beta], N odd")
                spec = LayerSpec(name, kind, lrn=(int(p[0]), float(p[1]), float(p[2]), float(p[3])))
            else:
                method = str(_field(layer, "method", "max"))
                if method != "max":
                    raise ValueError(f"pooling method {method!r} is not supported")
                spec = LayerSpec(
                    name,
                    kind,
                    pool=_pair(_field(layer, "pool"), "pool", 1),
                    stride=_pair(_field(layer, "stride"), "stride", 1),
                    pad=_pad4(_field(layer, "pad")),
                )
        except (ValueError, TypeError) as e:
            raise WeightsError(f"{where}: {e}") from e
        specs.append(spec)
    return specs


# ----------------------------------------------------------------------------- torch chain


class _Conv(nn.Module):
    def __init__(self, spec: LayerSpec) -> None:
        super().__init__()
        assert spec.weight is not None
        kh, kw, cin, cout = spec.weight.shape
        t, b, left, r = spec.pad
        sym = t == b and left == r
        self.conv = nn.Conv2d(
            cin, cout, (kh, kw), stride=spec.stride, padding=(t, left) if sym else 0
        )
        self.pad = None if sym else (left, r, t, b)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.pad is not None:
            x = nnf.pad(x, self.pad)
        return self.conv(x)


class _Relu(nn.Module):
    def __init__(self, leak: float) -> None:
        super().__init__()
        self.leak = leak

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nnf.leaky_relu(x, self.leak) if self.leak else nnf.relu(x)


class _MaxPool(nn.Module):
    def __init__(self, spec: LayerSpec) -> None:
        super().__init__()
        self.pool, self.stride = spec.pool, spec.stride
        t, b, left, r = spec.pad
        self.pad = (left, r, t, b) if any(spec.pad) else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.pad is not None:
            x = nnf.pad(x, self.pad, value=-math.inf)
        return nnf.max_pool2d(x, self.pool, self.stride)


def _lrn(spec: LayerSpec) -> nn.LocalResponseNorm:
    n, kappa, alpha, beta = spec.lrn
    return nn.LocalResponseNorm(n, alpha=alpha * n, beta=beta, k=kappa)


class SimpleNN(nn.Module):
    """A MatConvNet SimpleNN chain (conv / relu / lrn / max pool) built from specs.

    Built with random weights; :meth:`load_specs` copies the file's arrays in.
    """

    def __init__(self, specs: Sequence[LayerSpec]) -> None:
        super().__init__()
        self.names = [s.name for s in specs]
        mods: list[nn.Module] = []
        for s in specs:
            if s.kind == "conv":
                mods.append(_Conv(s))
            elif s.kind == "relu":
                mods.append(_Relu(s.leak))
            elif s.kind == "lrn":
                mods.append(_lrn(s))
            else:
                mods.append(_MaxPool(s))
        self.chain = nn.ModuleList(mods)

    def load_specs(self, specs: Sequence[LayerSpec]) -> None:
        """Copy conv weights (h, w, cin, cout) -> OIHW and biases into the chain."""
        with torch.no_grad():
            for mod, s in zip(self.chain, specs, strict=True):
                if isinstance(mod, _Conv):
                    assert s.weight is not None and s.bias is not None
                    assert mod.conv.bias is not None  # _Conv builds its Conv2d with a bias
                    w = np.ascontiguousarray(s.weight.transpose(3, 2, 0, 1))
                    mod.conv.weight.copy_(torch.from_numpy(w))
                    mod.conv.bias.copy_(torch.from_numpy(np.ascontiguousarray(s.bias)))

    def forward_maps(self, x: torch.Tensor, wanted: Collection[str]) -> dict[str, torch.Tensor]:
        """(B, C, H, W) -> {name: output of that layer} for ``wanted``; stops at the last one."""
        if not wanted:
            return {}
        last = max(self.names.index(n) for n in wanted)
        out: dict[str, torch.Tensor] = {}
        for i in range(last + 1):
            x = self.chain[i](x)
            if self.names[i] in wanted:
                out[self.names[i]] = x
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> output of the last layer."""
        return self.forward_maps(x, (self.names[-1],))[self.names[-1]]


# ----------------------------------------------------------------------------- VGG-M-1024

_C = "conv"
VGGM_LAYERS: list[tuple[str, str, tuple[int, ...] | None]] = [
    ("conv1", _C, (7, 7, 3, 96)),
    ("relu1", "relu", None),
    ("norm1", "lrn", None),
    ("pool1", "pool", None),
    ("conv2", _C, (5, 5, 96, 256)),
    ("relu2", "relu", None),
    ("norm2", "lrn", None),
    ("pool2", "pool", None),
    ("conv3", _C, (3, 3, 256, 512)),
    ("relu3", "relu", None),
    ("conv4", _C, (3, 3, 512, 512)),
    ("relu4", "relu", None),
    ("conv5", _C, (3, 3, 512, 512)),
    ("relu5", "relu", None),
]


def _average_image(norm: Any, path: Path) -> np.ndarray:
    """``averageImage`` as (1, 1, 3) or (H, W, 3) float64."""
    avg = getattr(norm, "averageImage", None) if norm is not None else None
    if avg is None:
        raise WeightsError(f"{str(path)!r}: no normalization.averageImage (meta.normalization)")
    a = np.asarray(avg, dtype=np.float64)
    if a.size == 3:
        return a.reshape(1, 1, 3)
    if a.ndim == 3 and a.shape[2] == 3:
        return a
    raise WeightsError(f"{str(path)!r}: averageImage has shape {a.shape}, expected (H, W, 3)")


@register_backbone
class VggM1024(MapsModuleBackbone):
    """VGG-M-1024 conv1-relu5 (MatConvNet); see the module docstring."""

    name = "vgg_m_1024"
    layers: ClassVar[dict[str, int]] = {"conv4": 512, "relu4": 512, "conv5": 512, "relu5": 512}
    default_input_size = (224, 224)
    weights_hint = (
        "Get imagenet-vgg-m-1024.mat from the MatConvNet pretrained models page "
        "(vlfeat.org/matconvnet/pretrained) and pass its path as weights."
    )

    def __init__(
        self,
        module: SimpleNN,
        device: str = "cpu",
        average_image: np.ndarray | None = None,
        image_size: tuple[int, int] = (224, 224),
    ) -> None:
        super().__init__(module, device)
        self.average_image = (
            np.zeros((1, 1, 3)) if average_image is None else np.asarray(average_image)
        )
        #: ``meta.normalization.imageSize`` (rows, cols) of the file.
        self.image_size = image_size
        self._means: dict[tuple[int, int], np.ndarray] = {}

    @classmethod
    def from_weights(cls, path: Path | None, device: str = "cpu", **options: Any) -> VggM1024:
        """Read the SimpleNN file, build conv1-relu5, then load the weights. No options."""
        path = cls.required_file(path, options)
        layers, norm = simplenn(load_mat(path), path)
        specs = parse_chain(path, layers, VGGM_LAYERS)
        average_image = _average_image(norm, path)
        size = getattr(norm, "imageSize", None)
        image_size = (224, 224)
        if size is not None and np.size(size) >= 2:
            image_size = (int(np.ravel(size)[0]), int(np.ravel(size)[1]))
        module = SimpleNN(specs)
        module.load_specs(specs)
        return cls(module, device, average_image, image_size)

    def _mean(self, size: tuple[int, int]) -> np.ndarray:
        a = self.average_image
        if a.shape[:2] == (1, 1) or a.shape[:2] == tuple(size):
            return a
        if size not in self._means:
            self._means[size] = imresize(a, size, "lanczos3")
        return self._means[size]

    def preprocess(self, image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """H x W x 3 RGB uint8 -> 3 x rows x cols float32: lanczos3 on floats, minus the mean."""
        size = (int(size[0]), int(size[1]))
        img = imresize(initcrop(rgb3(image)).astype(np.float64), size, "lanczos3")
        img = img - self._mean(size)
        return np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32)
