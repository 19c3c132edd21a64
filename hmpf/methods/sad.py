"""SAD (method id 2): SeqSLAM-style patch-normalised thumbnails, 64x32, 2048-D ``uint8``.

Spec §2.7 (docs/spec/other-methods.md): crop, ``imresize`` RGB to 32 rows x 64 columns (lanczos3),
``rgb2gray``, patch-normalise every 8x8 patch to ``round(255 (p - min) / (max - min))`` (a flat
patch gives 0), flatten column-major. Distance: mean absolute difference over the 2048 values, lower
is better.

``faithful=True`` reproduces the original's uint8 arithmetic, where ``db - q`` saturates at 0,
so only the one-sided sum ``sum(max(db - q, 0)) / 2048`` is computed. The default is the true
absolute difference (a deliberate fix, see spec §8.17).
"""

from __future__ import annotations

from typing import ClassVar

import cv2
import numpy as np
from pydantic import Field, model_validator

from hmpf.errors import ConfigError
from hmpf.imops import imresize, initcrop, rgb2gray, round_half_away
from hmpf.methods.base import (
    GlobalMethod,
    MethodConfig,
    MetricSpec,
    ReferenceFitConfig,
    euclidean,
    route_dba,
)
from hmpf.methods.registry import register


class SadConfig(ReferenceFitConfig):
    width: int = Field(64, ge=8)
    height: int = Field(32, ge=8)
    patch: int = Field(8, ge=2)
    faithful: bool = Field(False, description="one-sided uint8 difference, as the original")

    @model_validator(mode="after")
    def _check_faithful(self) -> SadConfig:
        if self.faithful and (self.whiten is not None or self.dba):
            raise ValueError("faithful SAD takes no whiten / dba (they are not the original's)")
        return self


def patch_normalise(grey: np.ndarray, patch: int) -> np.ndarray:
    """Min-max stretch every ``patch`` x ``patch`` tile to 0..255 (``uint8``); flat tiles -> 0."""
    h, w = grey.shape
    t = grey.astype(np.float64).reshape(h // patch, patch, w // patch, patch)
    lo = t.min(axis=(1, 3), keepdims=True)
    hi = t.max(axis=(1, 3), keepdims=True)
    rng = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(rng > 0, round_half_away(255.0 * (t - lo) / np.where(rng > 0, rng, 1)), 0)
    return out.reshape(h, w).astype(np.uint8)


@register
class Sad(GlobalMethod):
    name = "sad"
    higher_is_better = False
    Config: ClassVar[type[MethodConfig]] = SadConfig
    dim = 2048

    def __init__(self, config: SadConfig | None = None) -> None:
        super().__init__(config)
        c: SadConfig = self.config  # type: ignore[assignment]
        if c.width % c.patch or c.height % c.patch:
            raise ConfigError("method 'sad': width and height must be multiples of patch")
        self.dim = c.width * c.height

    def raw_descriptor(self, image: np.ndarray) -> np.ndarray:
        c: SadConfig = self.config  # type: ignore[assignment]
        grey = rgb2gray(imresize(initcrop(image), (c.height, c.width), "lanczos3"))
        return patch_normalise(grey, c.patch).ravel(order="F")

    @property
    def whitened(self) -> bool:
        """True with ``whiten``: float descriptors compared by Euclidean distance."""
        return self.config.whiten is not None  # type: ignore[attr-defined]

    def augment_references(self, matrix: np.ndarray) -> np.ndarray:
        """With ``dba`` on the uint8 thumbnails: the weighted mean of the route neighbours,
        rounded back to uint8 (no L2 normalisation: SAD compares raw grey values)."""
        c: SadConfig = self.config  # type: ignore[assignment]
        if self.whitened or not c.dba:
            return super().augment_references(matrix)
        x = route_dba(matrix, c.dba, normalise=False)
        return np.clip(np.rint(x), 0, 255).astype(np.uint8)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        if self.whitened:
            return euclidean(queries, references)
        c: SadConfig = self.config  # type: ignore[assignment]
        r = np.ascontiguousarray(references, dtype=np.uint8)
        q = np.ascontiguousarray(queries, dtype=np.uint8)
        out = np.empty((q.shape[0], r.shape[0]), dtype=np.float64)
        if r.shape[0] == 0:
            return out
        # uint8 SIMD in OpenCV: absdiff for |db - q|; subtract saturates at 0 exactly like
        # MATLAB's uint8 ``db - q`` (the faithful one-sided difference).
        op = cv2.subtract if c.faithful else cv2.absdiff
        for i, row in enumerate(q):
            diff = op(r, np.broadcast_to(row, r.shape).copy())
            out[i] = cv2.reduce(diff, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
        return out / r.shape[1]

    def faiss_metric(self) -> MetricSpec | None:
        """L1 over ``dim`` (the mean absolute difference); the faithful one-sided difference
        is no FAISS metric. Whitened: Euclidean (``l2``)."""
        if self.whitened:
            return MetricSpec("l2", 1.0)
        c: SadConfig = self.config  # type: ignore[assignment]
        return None if c.faithful else MetricSpec("l1", 1.0 / self.dim)
