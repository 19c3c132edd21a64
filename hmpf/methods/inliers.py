"""Geometric verification (``inliers``): inliers of a robust two-view model between KAZE matches.

Not in the original HMPF (an accuracy lever): the classic re-ranking step of retrieval and
localisation pipelines, as a local method usable in any tier.

**Features** are KAZE's (spec §2.3, docs/spec/kaze.md; :mod:`hmpf.methods.kaze`): grey, crop, 300 x
300 lanczos3, OpenCV KAZE with the MATLAB defaults, the ``max_keypoints`` strongest, keypoints
(x, y, size, angle, response) and unit descriptors at float16 precision. The extraction and the
stored arrays are KAZE's own code, and so is the descriptor cache entry: an ``inliers`` and a
``kaze`` with the same extraction settings share cached features. KAZE's ``descriptor``
option applies as well (``beblid`` / ``teblid`` / ``orb``: binary descriptors on the same
keypoints, matched by Hamming distance with the same rule).

**Matching** is KAZE's ``matchFeatures`` rule (:func:`~hmpf.methods.kaze.nearest_two`,
:func:`~hmpf.methods.kaze.match_mask`): a query keypoint's nearest reference keypoint by SSD
is a match when ``SSD1 <= 4 * match_threshold / 100`` and ``SSD1 / SSD2 <= max_ratio``. With
``unique`` (default) a reference keypoint keeps only its closest query match, so one
repeated structure cannot vote many times.

**Score** (higher is better): the number of matches consistent with a two-view model fitted
robustly by OpenCV on the keypoint positions (pixels of the 300 x 300 image):

* ``model: homography`` (default): ``cv2.findHomography``; ``fundamental``:
  ``cv2.findFundamentalMat``.
* ``estimator: magsac`` (default, ``cv2.USAC_MAGSAC``) or ``ransac`` (``cv2.RANSAC``), with
  ``ransac_threshold`` pixels, ``confidence`` and ``max_iters``.
* Fewer than ``min_matches`` matches (or a model that cannot be fitted) scores 0: an image
  without keypoints is a 0, never an error.

Deterministic: OpenCV's random generator is seeded with ``seed`` before every pair, so a pair
scores the same whatever else is scored and in whatever order. The default model and
threshold were chosen on the Gardens Point training parts (``docs/experiments/inliers.md``).
Scoring is a loop over the candidates (one model fit each), so it belongs in a tier that
scores a short candidate list.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field

from hmpf.methods.base import MethodConfig
from hmpf.methods.kaze import (
    Kaze,
    KazeBaseConfig,
    KazeConfig,
    KazeFeatures,
    KazeSet,
    match_mask,
    nearest_two_any,
)
from hmpf.methods.registry import register

__all__ = ["Inliers", "InliersConfig", "match_points"]

ESTIMATORS = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}


class InliersConfig(KazeBaseConfig):
    model: Literal["homography", "fundamental"] = "homography"
    estimator: Literal["magsac", "ransac"] = "magsac"
    ransac_threshold: float = Field(3.0, gt=0, description="pixels of the image_size frame")
    confidence: float = Field(0.999, gt=0, lt=1)
    max_iters: int = Field(1000, ge=1)
    min_matches: int = Field(8, ge=4, description="fewer matches score 0")
    unique: bool = Field(True, description="one match per reference keypoint")
    seed: int = Field(0, ge=0, description="OpenCV RNG seed, set before every pair")


def match_points(
    query: KazeFeatures,
    ref: KazeFeatures,
    *,
    match_threshold: float = 20.0,
    max_ratio: float = 0.7,
    unique: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Matched keypoint positions, closest match first: ``(query_xy, ref_xy)``, each (n, 2)
    float32 in the ``image_size`` frame (KAZE's matching rule; ``unique`` keeps a reference
    keypoint's closest query match only)."""
    if len(query) == 0 or len(ref) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    ssd1, ssd2, nearest = nearest_two_any(query.descriptors, ref.descriptors)
    idx = np.flatnonzero(
        match_mask(ssd1, ssd2, match_threshold=match_threshold, max_ratio=max_ratio)
    )
    idx = idx[np.argsort(ssd1[idx], kind="stable")]
    if unique and len(idx):
        _, first = np.unique(nearest[idx], return_index=True)
        idx = idx[np.sort(first)]
    return query.keypoints[idx, :2], ref.keypoints[nearest[idx], :2]


@register
class Inliers(Kaze):
    name = "inliers"
    higher_is_better = True
    version = "1"
    Config: ClassVar[type[MethodConfig]] = InliersConfig

    def descriptor_key(self) -> str:
        """The descriptor cache entry of a ``kaze`` with the same extraction settings: the
        features are the same arrays."""
        c: InliersConfig = self.config  # type: ignore[assignment]
        shared = KazeBaseConfig.model_fields
        return Kaze(KazeConfig(**{k: getattr(c, k) for k in shared})).cache_key()

    def pair_inliers(self, query: KazeFeatures, ref: KazeFeatures) -> int:
        """Inliers of the two-view model between one query and one reference (0 with fewer
        than ``min_matches`` matches or no model)."""
        c: InliersConfig = self.config  # type: ignore[assignment]
        src, dst = match_points(
            query,
            ref,
            match_threshold=c.match_threshold,
            max_ratio=c.max_ratio,
            unique=c.unique,
        )
        if len(src) < c.min_matches:
            return 0
        cv2.setRNGSeed(c.seed)
        method = ESTIMATORS[c.estimator]
        try:
            if c.model == "homography":
                model, mask = cv2.findHomography(
                    src, dst, method, c.ransac_threshold, maxIters=c.max_iters,
                    confidence=c.confidence,
                )  # fmt: skip
            else:
                model, mask = cv2.findFundamentalMat(
                    src, dst, method, c.ransac_threshold, c.confidence, c.max_iters
                )
        except cv2.error:  # degenerate configurations (all points collinear, ...)
            return 0
        if model is None or mask is None:
            return 0
        return int(np.count_nonzero(mask))

    def scores(
        self,
        query: KazeFeatures,
        references: KazeSet | Sequence[KazeFeatures],
        subset: np.ndarray | None = None,
    ) -> np.ndarray:
        """Inlier counts (float64) of ``query`` against each reference (or
        ``references[subset]``, in order); one model fit per reference."""
        refs: Any = references if isinstance(references, KazeSet) else self.stack(references)
        idx = np.arange(len(refs)) if subset is None else np.asarray(subset, np.int64)
        c: InliersConfig = self.config  # type: ignore[assignment]
        out = np.zeros(len(idx), dtype=np.float64)
        if len(query) < c.min_matches:
            return out
        for j, i in enumerate(idx):
            out[j] = self.pair_inliers(query, refs[int(i)])
        return out
