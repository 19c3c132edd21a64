"""HOG (method id 3): MATLAB ``extractHOGFeatures`` on a 300x300 grey image, 2916-D.

Spec §2.6 (docs/spec/hog.md): crop, ``imresize`` RGB to 300x300 (lanczos3), ``rgb2gray``, then HOG
with 30x30-pixel cells, 2x2-cell blocks overlapping by one cell, 9 unsigned orientation bins,
L2-Hys block normalisation: 9 x 9 blocks x 4 cells x 9 bins = 2916 values. Lower distance is
better (Euclidean).

Deviation (documented): OpenCV's ``HOGDescriptor`` computes the descriptor. It follows
Dalal-Triggs as MATLAB does (central-difference gradients, bin interpolation, trilinear
spatial interpolation inside a block, Gaussian block window, L2-Hys clipped at 0.2); we set the
Gaussian window to sigma = half the block width as the spec states (OpenCV's own default is a
quarter). MATLAB's exact interpolation details are not published (spec §8.16), and
OpenCV orders the values differently, which does not change any Euclidean distance.
"""

from __future__ import annotations

from typing import ClassVar

import cv2
import numpy as np
from pydantic import Field

from hmpf.errors import ConfigError
from hmpf.imops import imresize, initcrop, rgb2gray
from hmpf.methods.base import (
    GlobalMethod,
    MethodConfig,
    MetricSpec,
    ReferenceFitConfig,
    euclidean,
)
from hmpf.methods.registry import register


class HogConfig(ReferenceFitConfig):
    image_size: int = Field(300, ge=16, description="square resize before HOG (pixels)")
    cell_size: int = Field(30, ge=4)
    block_cells: int = Field(2, ge=1, description="block side in cells")
    bins: int = Field(9, ge=2)


@register
class Hog(GlobalMethod):
    name = "hog"
    higher_is_better = False
    Config: ClassVar[type[MethodConfig]] = HogConfig
    dim = 2916

    def __init__(self, config: HogConfig | None = None) -> None:
        super().__init__(config)
        c: HogConfig = self.config  # type: ignore[assignment]
        if c.image_size % c.cell_size:
            raise ConfigError("method 'hog': image_size must be a multiple of cell_size")
        block = c.cell_size * c.block_cells
        self._hog = cv2.HOGDescriptor(
            (c.image_size, c.image_size),
            (block, block),
            (c.cell_size, c.cell_size),
            (c.cell_size, c.cell_size),
            c.bins,
            1,  # derivAperture
            block / 2.0,  # winSigma: half the block width
            cv2.HOGDESCRIPTOR_L2HYS,
            0.2,
            False,  # no gamma correction
            64,
            False,  # unsigned gradients
        )
        cells = c.image_size // c.cell_size
        self.dim = (cells - c.block_cells + 1) ** 2 * c.block_cells**2 * c.bins

    def raw_descriptor(self, image: np.ndarray) -> np.ndarray:
        c: HogConfig = self.config  # type: ignore[assignment]
        grey = rgb2gray(imresize(initcrop(image), (c.image_size, c.image_size), "lanczos3"))
        return np.asarray(self._hog.compute(grey)).reshape(-1).astype(np.float32)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    def faiss_metric(self) -> MetricSpec:
        return MetricSpec("l2", 1.0)
