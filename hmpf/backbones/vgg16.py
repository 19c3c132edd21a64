"""VGG-16 + NetVLAD + WPCA, Pitts30k (Arandjelovic et al.), the NetVLAD backbone
(spec §2.5, docs/spec/netvlad.md).

Weights: the "structed" ``vd16_pitts30k_conv5_3_vlad_preL2_intra_white`` network,
``Pitts30K_struct.mat`` (made by uzh-rpg/netvlad_tf_open ``net_class2struct.m``, downloaded by
cvg/Hierarchical-Localization). The original file stores MATLAB classes that scipy cannot read.
It is read with ``loadmat(struct_as_record=False, squeeze_me=True)``; ``net.layers`` (0-based):

====  =============  ===================================================================
0-28  VGG-16 convs   conv (``weights = {W (3,3,cin,cout), b}``, pad 1) / relu / pool 2x2 s2,
                     ending with conv5_3 at 28 (no ReLU after it)
29    preL2          ``normalize``
30    vlad:core      ``custom``, ``weights = {assign (1,1,D,K), -centroids (1,1,D,K)}``
31    vlad:intranorm ``normalize``
32    postL2         ``custom``
33    WPCA           ``conv``, ``weights = {W (1,1,D*K,out), b (out,)}``
34    finalL2        ``custom``
====  =============  ===================================================================

The torch module is the conv part only; it exposes ``conv5_3`` (512 x 14 x 14 at 224 x 224).
The NetVLAD head is exposed as arrays by :meth:`Vgg16NetVLAD.netvlad_params` for the NetVLAD
method: ``assign`` (D, K), ``centroids`` (K, D) (the stored ``-centroids``, negated back and
transposed), ``wpca_w`` (D*K, out), ``wpca_b`` (out,). D, K and ``out`` are read from the arrays
(512, 64 and 4096 in the real file). Layers 29-34 are checked loosely: each must match the
expected name *or* type, layer 30 must hold two (D, K) arrays with D = 512, and the WPCA
weight must have D*K rows.

Preprocessing (HMPF ``SingleFeat``): crop (§1.3), MATLAB ``imresize`` lanczos3 to 224 x 224 on
uint8 (rounded), float32, minus ``meta.normalization.averageImage(1, 1, c)`` per channel, RGB.
Deviation **[U]**: the modified ``serialAllFeats`` HMPF actually called is unpublished and may
resize differently (§8.9).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from hmpf.backbones.base import MapsModuleBackbone, register_backbone, rgb3
from hmpf.backbones.vgg_m import SimpleNN, load_mat, parse_chain, simplenn
from hmpf.errors import WeightsError
from hmpf.imops import imresize, initcrop

__all__ = ["VGG16_LAYERS", "Vgg16NetVLAD"]


def _vgg16_layers() -> list[tuple[str, str, tuple[int, ...] | None]]:
    out: list[tuple[str, str, tuple[int, ...] | None]] = []
    cin = 3
    for block, (cout, n) in enumerate(((64, 2), (128, 2), (256, 3), (512, 3), (512, 3)), 1):
        for j in range(1, n + 1):
            out.append((f"conv{block}_{j}", "conv", (3, 3, cin, cout)))
            out.append((f"relu{block}_{j}", "relu", None))
            cin = cout
        out.append((f"pool{block}", "pool", None))
    return out[:-2]  # ends with conv5_3: no relu5_3, no pool5


#: (name, kind, MatConvNet W shape) of layers 0-28.
VGG16_LAYERS = _vgg16_layers()
assert len(VGG16_LAYERS) == 29 and VGG16_LAYERS[-1][0] == "conv5_3"

# Loose check of the head: (index, name token, type); one of the two must match.
_HEAD = [
    (29, "prel2", "normalize"),
    (30, "vlad", "custom"),
    (31, "intranorm", "normalize"),
    (32, "postl2", "custom"),
    (33, "wpca", "conv"),
    (34, "finall2", "custom"),
]


def _weights(layer: Any) -> list[np.ndarray]:
    ws = getattr(layer, "weights", None)
    if ws is None:
        return []
    if isinstance(ws, np.ndarray) and ws.dtype == object:
        return [np.asarray(w) for w in ws.ravel()]
    return [np.asarray(ws)]


def read_netvlad_head(path: Path, layers: list[Any]) -> dict[str, np.ndarray]:
    """NetVLAD and WPCA arrays of layers 29-34 (see the module docstring), float32."""
    if len(layers) < 35:
        raise WeightsError(
            f"{str(path)!r}: {len(layers)} layers, expected 35 "
            "(VGG-16 to conv5_3, preL2, vlad:core, intranorm, postL2, WPCA, finalL2)"
        )
    for i, token, ltype in _HEAD:
        name = str(getattr(layers[i], "name", ""))
        typ = str(getattr(layers[i], "type", ""))
        if token not in name.lower().replace(":", "").replace("_", "") and typ != ltype:
            raise WeightsError(
                f"{str(path)!r}: layer {i} is {name!r} of type {typ!r}, "
                f"expected {token!r} of type {ltype!r}"
            )
    d = VGG16_LAYERS[-1][2][3]  # type: ignore[index]
    vlad = _weights(layers[30])
    where = f"{str(path)!r}: layer 30 ({getattr(layers[30], 'name', 'vlad:core')!r})"
    if len(vlad) < 2:
        raise WeightsError(f"{where} has {len(vlad)} weight arrays, expected 2")
    assign, negc = (np.asarray(a, dtype=np.float32) for a in vlad[:2])
    if assign.ndim == 4 and assign.shape[:2] == (1, 1):
        assign = assign.reshape(assign.shape[2:])
    if assign.ndim != 2 or assign.shape[0] != d:
        raise WeightsError(f"{where}: assignment weights {assign.shape}, expected ({d}, K)")
    k = assign.shape[1]
    if negc.size != d * k:
        raise WeightsError(f"{where}: centroids {negc.shape}, expected ({d}, {k})")
    negc = negc.reshape(d, k)
    k_field = getattr(layers[30], "K", None)
    if k_field is not None and np.size(k_field) == 1 and int(k_field) != k:
        raise WeightsError(f"{where}: K = {int(k_field)} but the weights have {k} clusters")
    wpca = _weights(layers[33])
    where = f"{str(path)!r}: layer 33 ({getattr(layers[33], 'name', 'WPCA')!r})"
    if len(wpca) < 2:
        raise WeightsError(f"{where} has {len(wpca)} weight arrays, expected 2")
    b = np.asarray(wpca[1], dtype=np.float32).ravel()
    w = np.asarray(wpca[0], dtype=np.float32)
    if w.size != d * k * b.size:
        raise WeightsError(
            f"{where}: weight {w.shape} and bias {b.shape} do not fit (1, 1, {d * k}, out)"
        )
    return {
        "assign": assign,
        "centroids": np.ascontiguousarray(-negc.T),
        "wpca_w": w.reshape(d * k, b.size),  # drops (1, 1, ...) only: no copy of ~512 MB
        "wpca_b": b,
    }


def _channel_mean(norm: Any, path: Path) -> np.ndarray:
    """``averageImage(1, 1, :)`` as (3,) float32."""
    avg = getattr(norm, "averageImage", None) if norm is not None else None
    if avg is None:
        raise WeightsError(f"{str(path)!r}: no net.meta.normalization.averageImage")
    a = np.asarray(avg, dtype=np.float64)
    if a.size == 3:
        return a.reshape(3).astype(np.float32)
    if a.ndim == 3 and a.shape[2] == 3:
        return a[0, 0].astype(np.float32)
    raise WeightsError(f"{str(path)!r}: averageImage has shape {a.shape}, expected (1, 1, 3)")


@register_backbone
class Vgg16NetVLAD(MapsModuleBackbone):
    """VGG-16 to conv5_3 with the Pitts30k NetVLAD/WPCA head as arrays; see the module doc."""

    name = "vgg16"
    layers: ClassVar[dict[str, int]] = {"conv5_3": 512}
    default_input_size = (224, 224)
    weights_hint = (
        "Get Pitts30K_struct.mat (the 'structed' vd16_pitts30k_conv5_3_vlad_preL2_intra_white "
        "from Relja Arandjelovic's NetVLAD page, as used by cvg/Hierarchical-Localization) "
        "and pass its path as weights."
    )

    def __init__(
        self,
        module: SimpleNN,
        device: str = "cpu",
        mean: np.ndarray | None = None,
        head: dict[str, np.ndarray] | None = None,
    ) -> None:
        super().__init__(module, device)
        self.mean = np.zeros(3, np.float32) if mean is None else mean
        self._head = dict(head or {})

    @classmethod
    def from_weights(cls, path: Path | None, device: str = "cpu", **options: Any) -> Vgg16NetVLAD:
        """Read the struct .mat, build VGG-16 to conv5_3, then load the weights. No options."""
        path = cls.required_file(path, options)
        layers, norm = simplenn(load_mat(path), path)
        head = read_netvlad_head(path, layers)
        specs = parse_chain(path, layers, VGG16_LAYERS)
        mean = _channel_mean(norm, path)
        module = SimpleNN(specs)
        module.load_specs(specs)
        return cls(module, device, mean, head)

    def netvlad_params(self) -> dict[str, np.ndarray]:
        """NetVLAD + WPCA parameters, float32 (shared arrays: do not modify in place).

        Returns:
            ``assign`` (D, K) soft-assignment 1x1 conv (no bias), ``centroids`` (K, D),
            ``wpca_w`` (D*K, out) with input index ``k + K*d`` (k fastest), ``wpca_b`` (out,).
            Pitts30k: D = 512, K = 64, out = 4096.
        """
        return dict(self._head)

    def preprocess(self, image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """H x W x 3 RGB uint8 -> 3 x rows x cols float32 (uint8 lanczos3, minus the mean)."""
        img = imresize(initcrop(rgb3(image)), size, "lanczos3").astype(np.float32)
        return np.ascontiguousarray((img - self.mean).transpose(2, 0, 1))
