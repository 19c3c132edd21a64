"""HybridNet "CNNHeat" (method id 1): the conv5 max-location histogram, 169-D.

Spec §2.1 (docs/spec/hybridnet.md). For each channel of a 13 x 13 x C activation map ``A`` (rows =
image y, cols = image x) that is not all zero, the location of its maximum (MATLAB's tie rule: first
in column-major order, i.e. the smallest column, then the smallest row) votes into a 13 x 13
histogram at ``h[col, 12 - row]``; the feature is ``h`` flattened column-major (the vote goes
to index ``col + 13 * (12 - row)``). Counts sum to the number of non-zero channels. Euclidean
distance, lower is better. An all-zero map gives the zero vector (MATLAB would error).

Backbones:

* ``caffenet`` with ``HybridNet.caffemodel``: the exact pipeline (relu5 of a 227 x 227 input,
  ``mean_mode`` none by default, as HMPF).
* ``efficientnet_lite0`` (default): the same rule on stage 6 (``s6``, 192 channels, stride 32)
  of a 416 x 416 input, which is a 13 x 13 map (stage 5 at 208 x 208 and the head at 416 were
  weaker on Gardens Point). Stage 6 ends in a linear projection, so its activations are
  signed; the rule takes the maximum as it is (a channel is skipped only when its maximum is
  0, as in the original).
* ``efficientnet_lite1`` / ``efficientnet_lite2``: the same (the histogram needs 13 x 13).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from pydantic import Field

from hmpf.methods.base import GlobalMethod, MetricSpec, euclidean
from hmpf.methods.cnn import CnnConfig, CnnMethod
from hmpf.methods.registry import register

GRID = 13
DEFAULTS = {
    "caffenet": ("relu5", (227, 227)),
    "efficientnet_lite0": ("s6", (416, 416)),
    "efficientnet_lite1": ("s6", (416, 416)),
    "efficientnet_lite2": ("s6", (416, 416)),
}


def max_location_histogram(a: np.ndarray) -> np.ndarray:
    """(C, 13, 13) activations -> (169,) float32 vote counts (spec §2.1 rules).

    Raises:
        ValueError: the map is not 13 x 13.
    """
    c, h, w = a.shape
    if (h, w) != (GRID, GRID):
        raise ValueError(f"HybridNet needs a {GRID}x{GRID} map, got {h}x{w}")
    # Column-major flattening per channel: index = col * 13 + row; argmax takes the first.
    flat = a.transpose(0, 2, 1).reshape(c, -1)
    k = flat.argmax(axis=1)
    live = flat.max(axis=1) != 0
    col, row = k // GRID, k % GRID
    votes = col[live] + GRID * (GRID - 1 - row[live])
    return np.bincount(votes, minlength=GRID * GRID).astype(np.float32)


class HybridNetConfig(CnnConfig):
    layer: str | None = Field(None, description="13x13 map; None = the backbone's default")


@register
class HybridNet(CnnMethod, GlobalMethod):
    name = "hybridnet"
    higher_is_better = False
    version = "1"
    Config: ClassVar[type[CnnConfig]] = HybridNetConfig
    dim = GRID * GRID

    def _default(self) -> tuple[str, tuple[int, int]]:
        backbone = self.cnn.backbone
        if backbone not in DEFAULTS:
            raise ValueError(f"hybridnet has no default layer for backbone {backbone!r}")
        return DEFAULTS[backbone]

    def layers(self) -> list[str]:
        layer = self.config.layer  # type: ignore[attr-defined]
        return [layer or self._default()[0]]

    def default_input_size(self) -> tuple[int, int]:
        return self._default()[1]

    def from_maps(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        return max_location_histogram(maps[self.layers()[0]])

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    def faiss_metric(self) -> MetricSpec:
        return MetricSpec("l2", 1.0)
