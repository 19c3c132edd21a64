"""GeM: a generalised-mean pooled global descriptor on a CNN backbone (not in the paper).

``g_c = (mean_{x,y} max(A_c, eps)^p)^(1/p)`` over one feature map, then L2-normalised
(Radenovic et al., TPAMI 2018). Cheap and strong for tier 1: one vector per image, Euclidean
distance (lower is better), FAISS-friendly.

Options (accuracy levers; off by default): ``scales`` (multi-scale: the mean of the L2-normalised
descriptors of every input scale, :class:`~hmpf.methods.cnn.MultiScaleConfig`) and ``crops``
(multi-crop: R-MAC's region grid with GeM pooling, Tolias et al., ICLR 2016: the whole map
plus square crops of ``crops`` levels, :func:`crop_boxes`, each pooled and L2-normalised,
summed, L2-normalised).

Values are kept at float16 precision (what the index stores). Default layer per backbone:
EfficientNet-Lite0 / Lite1 / Lite2 ``head`` (1280-d, at the backbone's ImageNet input size),
VGG16 ``conv5_3`` (512-d, through a ReLU), CaffeNet ``relu5`` (256-d), VGG-M ``relu5``
(512-d).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import ClassVar

import numpy as np
from pydantic import Field

from hmpf.methods.base import GlobalMethod, MetricSpec, ReferenceFitConfig, euclidean
from hmpf.methods.cnn import CnnConfig, CnnMethod, MultiScaleConfig
from hmpf.methods.kaze import half
from hmpf.methods.registry import register

DEFAULT_LAYER = {
    "efficientnet_lite0": "head",
    "efficientnet_lite1": "head",
    "efficientnet_lite2": "head",
    "vgg16": "conv5_3",
    "caffenet": "relu5",
    "vgg_m_1024": "relu5",
}


class GemConfig(MultiScaleConfig, ReferenceFitConfig):
    layer: str | None = Field(None, description="backbone map; None = the backbone's default")
    p: float = Field(3.0, ge=1.0, le=32.0)
    eps: float = Field(1e-6, gt=0)
    crops: int = Field(0, ge=0, le=4, description="R-MAC crop levels (0: the whole map only)")


def _unit(g: np.ndarray) -> np.ndarray:
    return g / max(float(np.linalg.norm(g)), 1e-12)


def crop_boxes(h: int, w: int, levels: int) -> list[tuple[int, int, int, int]]:
    """Regions ``(y0, x0, y1, x1)`` of an ``h x w`` map: the whole map, then for each level
    ``l = 1..levels`` squares of side ``2 min(h, w) / (l + 1)`` (halves rounded up, at least
    1) laid evenly along each axis (start offsets rounded the same way), as many as keep
    neighbours overlapping by about 40 % (``1 + ceil((a - side) / (0.6 side))`` along an
    axis of length ``a``; ``l`` along the shorter one). Duplicates are dropped; order is
    deterministic."""
    boxes = [(0, 0, h, w)]
    short = min(h, w)
    for level in range(1, levels + 1):
        side = max(1, int(2.0 * short / (level + 1) + 0.5))
        starts = []
        for a in (h, w):
            n = 1 if a <= side else 1 + int(np.ceil((a - side) / (0.6 * side)))
            starts.append(sorted({int(v + 0.5) for v in np.linspace(0, max(0, a - side), n)}))
        for y in starts[0]:
            for x in starts[1]:
                box = (y, x, min(h, y + side), min(w, x + side))
                if box not in boxes:
                    boxes.append(box)
    return boxes


@register
class Gem(CnnMethod, GlobalMethod):
    name = "gem"
    higher_is_better = False
    version = "2"  # 2: float16-precision descriptors
    Config: ClassVar[type[CnnConfig]] = GemConfig
    dim = 0  # unknown until the first descriptor (the backbone layer's channels)

    @property
    def gem(self) -> GemConfig:
        return self.config  # type: ignore[return-value]

    def layers(self) -> list[str]:
        return [self.gem.layer or DEFAULT_LAYER[self.gem.backbone]]

    def default_input_size(self) -> tuple[int, int]:
        # 224 x 224 beat 288 x 512 on Gardens Point (recall@1 0.61 vs 0.57 day->night).
        return super().default_input_size()

    def _gem(self, a: np.ndarray) -> np.ndarray:
        """L2-normalised GeM of one (C, h, w) float32 map (its crops with ``crops``)."""
        p = self.gem.p
        x = np.power(np.maximum(a, self.gem.eps), p)
        if self.gem.crops:
            boxes = crop_boxes(a.shape[1], a.shape[2], self.gem.crops)
            regions = [x[:, y0:y1, x0:x1].mean(axis=(1, 2)) for y0, x0, y1, x1 in boxes]
            g = np.sum([_unit(r ** (1.0 / p)) for r in regions], axis=0)
        else:
            g = x.mean(axis=(1, 2)) ** (1.0 / p)
        return _unit(g)

    def _pooled(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        per = [self._gem(m[self.layers()[0]].astype(np.float32)) for m in self.scale_maps(maps)]
        return half(per[0] if len(per) == 1 else _unit(np.mean(per, axis=0)))

    def from_maps(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        """The descriptor at float16 precision; whitened (``whiten``) after pooling."""
        return self.finish(self._pooled(maps))

    def finish(self, descriptor: np.ndarray) -> np.ndarray:
        """Whitened (``whiten``) and rounded to float16 precision again."""
        if self.gem.whiten is None:
            return descriptor
        return half(super().finish(np.asarray(descriptor, dtype=np.float32)))

    def fit_from_maps(self, samples: Sequence[Mapping[str, np.ndarray]]) -> None:
        """Fit the whitening on the references' pooled descriptors."""
        self.fit_references(np.stack([self._pooled(maps) for maps in samples]))

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    def faiss_metric(self) -> MetricSpec:
        return MetricSpec("l2", 1.0)
