"""GeM: a generalised-mean pooled global descriptor on a CNN backbone (not in the paper).

``g_c = (mean_{x,y} max(A_c, eps)^p)^(1/p)`` over one feature map, then L2-normalised
(Radenovic et al., TPAMI 2018). Cheap and strong for tier 1: one vector per image, Euclidean
distance (lower is better), FAISS-friendly.

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
from hmpf.methods.cnn import CnnConfig, CnnMethod
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


class GemConfig(CnnConfig, ReferenceFitConfig):
    layer: str | None = Field(None, description="backbone map; None = the backbone's default")
    p: float = Field(3.0, ge=1.0, le=32.0)
    eps: float = Field(1e-6, gt=0)


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

    def _pooled(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        a = maps[self.layers()[0]].astype(np.float32)  # (C, h, w)
        p = self.gem.p
        g = np.power(np.maximum(a, self.gem.eps), p).mean(axis=(1, 2)) ** (1.0 / p)
        return half(g / max(float(np.linalg.norm(g)), 1e-12))

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
