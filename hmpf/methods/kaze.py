"""KAZE (method id 9): matched-feature residual, the sum of the 20 strongest matches.

Spec §2.3 (docs/spec/kaze.md). Extraction: ``rgb2gray``, crop, ``imresize`` to 300x300 (lanczos3,
uint8), OpenCV KAZE with MATLAB ``detectKAZEFeatures`` defaults (threshold 1e-4, 3 octaves, 4
levels, Perona-Malik g2 "region" diffusion, 64-D oriented descriptors). Descriptors are stored
L2-normalised to unit length, as ``matchFeatures`` normalises them before matching.

Matching reproduces MATLAB ``matchFeatures(Fq, Fdb, 'MatchThreshold', 20, 'MaxRatio', 0.7)``:
exhaustive search on SSD (squared Euclidean distance, ``2 - 2 q.d`` for unit vectors, range
[0, 4]); a query feature's nearest reference feature is a match if ``SSD1 <= 4 * 20 / 100 = 0.8``
and, when the reference has more than one feature, ``SSD1 / SSD2 <= 0.7`` (ratio on the squared
distances). Matches need not be unique. The pair's distance is the sum of the 20 smallest
match SSDs, padded with 1.0 when there are fewer than 20 (range [0, 20], lower is better; an
image without keypoints gives 20).

Deviations (documented):

* ``max_keypoints`` keeps the strongest keypoints by detector response (``None`` = all, as the
  original). The default caps at 500, which holds matching under 1 ms per image pair on
  Gardens Point (night frames have 800-1200 keypoints otherwise); ``configs/paper-*.yaml`` use
  ``None``.
* When ``SSD2 == 0`` the ratio ``SSD1 / SSD2`` is undefined; the match is rejected (MATLAB's
  NaN comparison would reject it as well) [U].
* MATLAB's KAZE implementation may differ numerically from OpenCV's (spec §8.15).
* Keypoints and unit descriptors are rounded to float16 precision (what the index stores);
  descriptor norms are then 1 to within 1e-3, and SSDs are computed exactly on those stored
  values (``|q|^2 + |d|^2 - 2 q.d``), not as ``2 - 2 q.d``.

Binary descriptors (a lever beyond the paper): ``descriptor: beblid | teblid | orb`` describes
the same keypoints (KAZE's detection and orientation, the same ``max_keypoints`` strongest)
with a binary descriptor of OpenCV contrib (``cv2.xfeatures2d``) instead of KAZE's 64 floats:

* ``beblid`` / ``teblid``: BEBLID (Suarez et al. 2020) / TEBLID (2021), boosted binary
  descriptors learned on UBC patches; ``descriptor_bits`` 256 or 512 (unset: OpenCV's default,
  512 for BEBLID, 256 for TEBLID); ``scale_factor`` the sampling window, unset = 6.25, OpenCV's
  documented value for KAZE (and SURF) keypoints (1.0 is ORB's, 6.75 SIFT's, 5.0 AKAZE's).
* ``orb``: ORB's rotated BRIEF (256 bits) on the same keypoints at the 300 x 300 level (the
  keypoints' octave is reset to 0; patch 31 px; keypoints too close to the border are
  dropped), a baseline.

Descriptors are stored as packed bits (uint8, 32 or 64 bytes a keypoint). A binary descriptor
of ``b`` bits read as a unit vector of +-1/sqrt(b) entries has ``SSD = 4 * hamming / b``, so
matching is KAZE's rule unchanged on that SSD (the threshold is a percentage of the range, the
ratio test compares Hamming distances, and the sum and padding are the same); the Hamming
distances are computed by ``cv2.batchDistance`` (exact integers). The default ``kaze`` keeps
its behaviour, stored arrays and cache key: the new options are left out of the config's dump
while unset.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field, SerializerFunctionWrapHandler, model_serializer, model_validator

from hmpf.imops import imresize, initcrop, rgb2gray
from hmpf.methods.base import LocalMethod, MethodConfig
from hmpf.methods.registry import register

DESC_DIM = 64

Descriptor = Literal["kaze", "beblid", "teblid", "orb"]
#: Binary descriptors' default bit counts (OpenCV's defaults) and the bit counts they offer.
BINARY_BITS: dict[str, tuple[int, tuple[int, ...]]] = {
    "beblid": (512, (256, 512)),
    "teblid": (256, (256, 512)),
    "orb": (256, (256,)),
}
#: BEBLID / TEBLID ``scale_factor`` for KAZE keypoints (OpenCV's documentation).
KAZE_SCALE_FACTOR = 6.25
#: Options added after the first index format: left out of the dump while unset (None).
_LATER_OPTIONS = ("descriptor_bits", "scale_factor")


class KazeBaseConfig(MethodConfig):
    """How KAZE features are extracted and which nearest neighbours are matches: what every
    method built on KAZE features shares (``kaze``, ``inliers``)."""

    image_size: int = Field(300, ge=32)
    threshold: float = Field(1e-4, gt=0)
    octaves: int = Field(3, ge=1)
    octave_layers: int = Field(4, ge=1)
    max_keypoints: int | None = Field(500, ge=1, description="strongest kept; None = all")
    match_threshold: float = Field(20.0, gt=0, le=100, description="percent of the SSD range")
    max_ratio: float = Field(0.7, gt=0, le=1)
    descriptor: Descriptor = Field(
        "kaze", description="kaze (64 floats) or a binary one on the same keypoints"
    )
    descriptor_bits: Literal[256, 512] | None = Field(
        None, description="binary descriptors only; None = OpenCV's default"
    )
    scale_factor: float | None = Field(
        None, gt=0, description="beblid / teblid sampling window; None = 6.25 (KAZE keypoints)"
    )

    @model_validator(mode="after")
    def _descriptor_options(self) -> KazeBaseConfig:
        d = self.descriptor
        if (
            self.descriptor_bits is not None
            and self.descriptor_bits not in BINARY_BITS.get(d, (0, ()))[1]
        ):
            raise ValueError(
                f"descriptor_bits {self.descriptor_bits} is not offered by descriptor {d!r}"
                + (f" (one of {BINARY_BITS[d][1]})" if d in BINARY_BITS else " (binary only)")
            )
        if self.scale_factor is not None and d not in ("beblid", "teblid"):
            raise ValueError(f"scale_factor applies to beblid / teblid, not to {d!r}")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # The descriptor options at their defaults are left out: the default config dumps (and
        # so keys caches and records indexes) exactly as before they existed.
        data: dict[str, Any] = handler(self)
        if data.get("descriptor") == "kaze":
            data.pop("descriptor")
        for k in _LATER_OPTIONS:
            if data.get(k, 0) is None:
                data.pop(k)
        return data

    @property
    def binary(self) -> bool:
        return self.descriptor != "kaze"

    @property
    def bits(self) -> int:
        """Bits of a binary descriptor (64 floats: 0)."""
        if not self.binary:
            return 0
        return self.descriptor_bits or BINARY_BITS[self.descriptor][0]


class KazeConfig(KazeBaseConfig):
    n_best: int = Field(20, ge=1, description="matches summed")
    pad_value: float = Field(1.0, ge=0, description="SSD used for missing matches")


@dataclass(frozen=True)
class KazeFeatures:
    """Keypoints (n, 5: x, y, size, angle, response), float32, and descriptors: unit float32
    (n, 64) for KAZE's, packed bits uint8 (n, bits / 8) for a binary one."""

    keypoints: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return int(self.descriptors.shape[0])


@dataclass(frozen=True)
class KazeSet:
    """Reference features packed as ragged arrays: rows of every image concatenated.

    ``descriptors[offsets[i]:offsets[i + 1]]`` are image ``i``'s unit descriptors (float32,
    64 wide) and the same rows of ``keypoints`` its keypoints; the layout the index stores.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    offsets: np.ndarray

    @classmethod
    def from_features(
        cls,
        features: Sequence[KazeFeatures],
        width: int = DESC_DIM,
        dtype: type[np.generic] = np.float32,
    ) -> KazeSet:
        """Pack ``features``; ``width`` and ``dtype`` are the descriptors' (64 float32, or
        bits / 8 uint8), used when there is no feature."""
        counts = np.array([len(f) for f in features], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        if len(features) == 0:
            return cls(np.zeros((0, 5), np.float32), np.zeros((0, width), dtype), offsets)
        return cls(
            np.concatenate([f.keypoints for f in features]).astype(np.float32, copy=False),
            np.concatenate([f.descriptors for f in features]).astype(dtype, copy=False),
            offsets,
        )

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)

    @cached_property
    def sq_norms(self) -> np.ndarray:
        """(rows,) float64 squared norm of every descriptor (computed once per set)."""
        return (self.descriptors.astype(np.float64) ** 2).sum(axis=1)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, i: int) -> KazeFeatures:
        a, b = self.offsets[i], self.offsets[i + 1]
        return KazeFeatures(self.keypoints[a:b], self.descriptors[a:b])


def half(x: np.ndarray) -> np.ndarray:
    """float32 values rounded to float16 precision (finite inputs of moderate range)."""
    return np.asarray(x, dtype=np.float32).astype(np.float16).astype(np.float32)


def unit_rows(x: np.ndarray) -> np.ndarray:
    """L2-normalise each row (zero rows stay zero)."""
    x = np.asarray(x, dtype=np.float32)
    n = np.linalg.norm(x, axis=1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def best_two_ssd(query: np.ndarray, refs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest and second-nearest SSD of each query row among ``refs`` (unit vectors).

    Returns ``(ssd1, ssd2)`` of shape (nq,); ``ssd2`` is ``inf`` when ``refs`` has one row and
    both are ``inf`` when it has none.
    """
    nq = query.shape[0]
    if refs.shape[0] == 0:
        inf = np.full(nq, np.inf)
        return inf, inf.copy()
    qn = (query.astype(np.float64) ** 2).sum(axis=1)[:, None]
    rn = (refs.astype(np.float64) ** 2).sum(axis=1)[None, :]
    ssd = np.maximum(qn + rn - 2.0 * (query @ refs.T).astype(np.float64), 0.0)
    if refs.shape[0] == 1:
        return ssd[:, 0], np.full(nq, np.inf)
    two = np.partition(ssd, 1, axis=1)[:, :2]
    return two[:, 0], two[:, 1]


def nearest_two(query: np.ndarray, refs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest and second-nearest reference row of each query row, with their SSDs.

    Rows are ranked in float32 by ``q.d - |d|^2 / 2`` (as :meth:`Kaze.scores` ranks them:
    ``SSD = |q|^2 - 2 (q.d - |d|^2 / 2)``), one matrix product and two argmax passes; the two
    picks' SSDs are then computed exactly in float64, so they equal :func:`best_two_ssd`'s
    except on near-ties of the ranking.

    Returns ``(ssd1, ssd2, nearest)``, each (nq,): ``ssd2`` is ``inf`` when ``refs`` has one
    row, both are ``inf`` (and ``nearest`` 0) when it has none; ``nearest`` is int64.
    """
    nq = query.shape[0]
    if refs.shape[0] == 0:
        inf = np.full(nq, np.inf)
        return inf, inf.copy(), np.zeros(nq, np.int64)
    q64, r64 = query.astype(np.float64), refs.astype(np.float64)
    qn, rn = (q64 * q64).sum(axis=1), (r64 * r64).sum(axis=1)
    sim = np.asarray(query, np.float32) @ np.asarray(refs, np.float32).T
    sim -= (0.5 * rn).astype(np.float32)[None, :]
    rows = np.arange(nq)
    nearest = sim.argmax(axis=1)

    def ssd(j: np.ndarray) -> np.ndarray:
        return np.maximum(qn + rn[j] - 2.0 * np.einsum("ij,ij->i", q64, r64[j]), 0.0)

    if refs.shape[0] == 1:
        return ssd(nearest), np.full(nq, np.inf), nearest
    sim[rows, nearest] = -np.inf  # remove one maximum; a tied maximum stays
    return ssd(nearest), ssd(sim.argmax(axis=1)), nearest


def hamming_nearest_two(
    query: np.ndarray, refs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`nearest_two` for packed binary descriptors (uint8 rows of ``b / 8`` bytes).

    Hamming distances ``h`` (exact, ``cv2.batchDistance``) as the SSD of the +-1/sqrt(b)
    unit vectors the bits stand for: ``SSD = 4 * h / b`` (range [0, 4], as KAZE's). Returns
    ``(ssd1, ssd2, nearest)``, each (nq,), with :func:`nearest_two`'s conventions (``inf``
    for a missing neighbour, ``nearest`` 0 without references); ties keep the lower index.
    """
    nq, nr = query.shape[0], refs.shape[0]
    if nr == 0 or nq == 0:
        inf = np.full(nq, np.inf)
        return inf, inf.copy(), np.zeros(nq, np.int64)
    if query.dtype != np.uint8 or refs.dtype != np.uint8 or query.shape[1] != refs.shape[1]:
        raise ValueError(
            f"binary descriptors must be uint8 of one width, got {query.dtype} {query.shape} "
            f"and {refs.dtype} {refs.shape}"
        )
    k = min(2, nr)
    dist, idx = cv2.batchDistance(query, refs, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=k)
    unit = 4.0 / (8 * query.shape[1])
    ssd = dist.astype(np.float64) * unit
    ssd2 = ssd[:, 1] if k == 2 else np.full(nq, np.inf)
    return ssd[:, 0], ssd2, idx[:, 0].astype(np.int64)


def nearest_two_any(
    query: np.ndarray, refs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`hamming_nearest_two` for binary (uint8) descriptors, else :func:`nearest_two`."""
    if query.dtype == np.uint8:
        return hamming_nearest_two(query, refs)
    return nearest_two(query, refs)


def match_mask(
    ssd1: np.ndarray, ssd2: np.ndarray, *, match_threshold: float = 20.0, max_ratio: float = 0.7
) -> np.ndarray:
    """Which nearest neighbours are matches (``matchFeatures``' rule): ``ssd1 <= 4 *
    match_threshold / 100`` and ``ssd1 / ssd2 <= max_ratio`` (an infinite ``ssd2`` passes,
    ``0 / 0`` does not)."""
    thr = 4.0 * match_threshold / 100.0
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio_ok = (ssd1 / ssd2) <= max_ratio  # inf second-best: ratio 0 -> kept; 0/0 -> False
    return (ssd1 <= thr) & ratio_ok


def match_distance(
    ssd1: np.ndarray,
    ssd2: np.ndarray,
    *,
    match_threshold: float = 20.0,
    max_ratio: float = 0.7,
    n_best: int = 20,
    pad_value: float = 1.0,
) -> np.ndarray:
    """Fusion distance from best-two SSDs; leading axes are pairs, the last axis query rows.

    A query row matches when ``ssd1 <= 4 * match_threshold / 100`` and ``ssd1 / ssd2 <=
    max_ratio``; the result is the sum of the ``n_best`` smallest matched SSDs, each missing
    match counted as ``pad_value``.
    """
    keep = match_mask(ssd1, ssd2, match_threshold=match_threshold, max_ratio=max_ratio)
    vals = np.where(keep, ssd1, pad_value)
    nq = vals.shape[-1]
    take = min(n_best, nq)
    if take == 0:
        return np.full(vals.shape[:-1], n_best * pad_value)
    best = np.partition(vals, take - 1, axis=-1)[..., :take] if take < nq else vals
    # Missing matches were written as pad_value; only kept matches below it improve the sum.
    best = np.minimum(best, pad_value)
    return best.sum(axis=-1) + (n_best - take) * pad_value


@register
class Kaze(LocalMethod):
    name = "kaze"
    higher_is_better = False
    version = "3"  # 3: float16-precision keypoints and descriptors
    Config: ClassVar[type[MethodConfig]] = KazeConfig

    def __init__(self, config: KazeConfig | None = None) -> None:
        super().__init__(config)
        self._detector: Any = None

        self._describer: Any = None

    @property
    def detector(self) -> Any:
        if self._detector is None:
            c: KazeConfig = self.config  # type: ignore[assignment]
            self._detector = cv2.KAZE.create(
                extended=False,
                upright=False,
                threshold=c.threshold,
                nOctaves=c.octaves,
                nOctaveLayers=c.octave_layers,
                diffusivity=cv2.KAZE_DIFF_PM_G2,
            )
        return self._detector

    @property
    def describer(self) -> Any:
        """The binary descriptor extractor (``descriptor`` other than ``kaze``)."""
        if self._describer is None:
            c: KazeConfig = self.config  # type: ignore[assignment]
            scale = KAZE_SCALE_FACTOR if c.scale_factor is None else c.scale_factor
            if c.descriptor in ("beblid", "teblid"):  # BEBLID / TEBLID: one API, two models
                name = c.descriptor.upper()
                size = getattr(cv2.xfeatures2d, f"{name}_SIZE_{c.bits}_BITS")
                self._describer = getattr(cv2.xfeatures2d, name).create(scale, size)
            else:
                self._describer = cv2.ORB.create()
        return self._describer

    def _empty(self) -> KazeFeatures:
        c: KazeConfig = self.config  # type: ignore[assignment]
        if c.binary:
            return KazeFeatures(np.zeros((0, 5), np.float32), np.zeros((0, c.bits // 8), np.uint8))
        return KazeFeatures(np.zeros((0, 5), np.float32), np.zeros((0, DESC_DIM), np.float32))

    def _extract(self, image: np.ndarray) -> KazeFeatures:
        c: KazeConfig = self.config  # type: ignore[assignment]
        grey = imresize(initcrop(rgb2gray(image)), (c.image_size, c.image_size), "lanczos3")
        # KAZE's descriptors are computed for binary ones too: they give the keypoints their
        # orientation (KAZE's detect alone leaves the angle at 0).
        kps, desc = self.detector.detectAndCompute(grey, None)
        if desc is None or len(kps) == 0:
            return self._empty()
        kp = np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in kps], np.float32)
        order = np.arange(len(kp))
        if c.max_keypoints is not None and len(kp) > c.max_keypoints:
            order = np.argsort(-kp[:, 4], kind="stable")[: c.max_keypoints]
            order.sort()
            kp, desc = kp[order], desc[order]
        if c.binary:
            return self._describe_binary(grey, [kps[i] for i in order])
        # Stored at float16 precision (the index keeps float16 descriptors, 2 bytes a value),
        # so in-memory evaluation and the index score exactly the same values.
        return KazeFeatures(half(kp), half(unit_rows(desc)))

    def _describe_binary(self, grey: np.ndarray, kps: list[Any]) -> KazeFeatures:
        """Binary descriptors of the kept keypoints (the describer may drop some)."""
        c: KazeConfig = self.config  # type: ignore[assignment]
        if c.descriptor == "orb":
            for k in kps:
                k.octave = 0  # KAZE's octave is not an ORB pyramid level
        kps, desc = self.describer.compute(grey, kps)
        if desc is None or len(kps) == 0:
            return self._empty()
        kp = np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in kps], np.float32)
        return KazeFeatures(half(kp), np.ascontiguousarray(desc, dtype=np.uint8))

    def to_arrays(self, feature: KazeFeatures) -> dict[str, np.ndarray]:
        return {"keypoints": feature.keypoints, "descriptors": feature.descriptors}

    def from_arrays(self, arrays: dict[str, np.ndarray]) -> KazeFeatures:
        c: KazeConfig = self.config  # type: ignore[assignment]
        return KazeFeatures(
            np.asarray(arrays["keypoints"], np.float32),
            np.asarray(arrays["descriptors"], np.uint8 if c.binary else np.float32),
        )

    def _distance(self, ssd1: np.ndarray, ssd2: np.ndarray) -> np.ndarray:
        c: KazeConfig = self.config  # type: ignore[assignment]
        return match_distance(
            ssd1,
            ssd2,
            match_threshold=c.match_threshold,
            max_ratio=c.max_ratio,
            n_best=c.n_best,
            pad_value=c.pad_value,
        )

    def stack(self, features: Sequence[KazeFeatures]) -> KazeSet:
        c: KazeConfig = self.config  # type: ignore[assignment]
        if c.binary:
            return KazeSet.from_features(features, c.bits // 8, np.uint8)
        return KazeSet.from_features(features)

    def scores(
        self,
        query: KazeFeatures,
        references: KazeSet | Sequence[KazeFeatures],
        subset: np.ndarray | None = None,
    ) -> np.ndarray:
        """Distances of ``query`` to each reference (or to ``references[subset]``).

        Vectorised over references: sorted by descriptor count, they are gathered in chunks
        into padded (m, n_max, 65) blocks whose extra coordinate is ``-|d|^2 / 2``; with the
        query row's extra coordinate 1, one matrix product gives ``s = q.d - |d|^2 / 2``, so
        ``SSD = |q|^2 - 2 s`` (exact for the stored, nearly unit, float16-precision values),
        and an argmax / mask / max pass each query row's best two per reference; padding rows
        (extra coordinate -1e9) never win. No Python loop over references.

        Binary descriptors: one ``cv2.batchDistance`` (Hamming, best two) per reference
        (:func:`hamming_nearest_two`), then the same distance in one vectorised pass.
        """
        refs = references if isinstance(references, KazeSet) else self.stack(references)
        idx = np.arange(len(refs)) if subset is None else np.asarray(subset, np.int64)
        nq = query.descriptors.shape[0]
        c: KazeConfig = self.config  # type: ignore[assignment]
        out = np.full(len(idx), c.n_best * c.pad_value)  # no descriptor: no match
        counts = refs.counts[idx]
        if nq == 0:
            return out
        if c.binary:
            return self._scores_binary(query, refs, idx, out)
        # An extra coordinate carries -|d|^2 / 2 for real rows and -1e9 for padding rows, so
        # padding is never among the best two and needs no separate mask.
        q = np.empty((nq, DESC_DIM + 1), dtype=np.float32)
        q[:, :DESC_DIM] = query.descriptors
        q[:, DESC_DIM] = 1.0
        qn = (query.descriptors.astype(np.float64) ** 2).sum(axis=1)
        # References in order of descriptor count, so each chunk pads to a similar length;
        # chunks keep the similarity block (nq x rows) and the packed block near 32 MB.
        order = np.argsort(counts, kind="stable")
        order = order[counts[order] > 0]
        s = 0
        while s < len(order):
            n_max = int(counts[order[min(len(order) - 1, s + 1023)]])
            step = max(1, min(1024, 8_000_000 // (max(nq, DESC_DIM + 1) * n_max)))
            part = order[s : s + step]
            n_max = int(counts[part[-1]])
            out[part] = self._score_block(q, qn, refs, idx[part], counts[part], n_max)
            s += step
        return out

    def _scores_binary(
        self, query: KazeFeatures, refs: KazeSet, idx: np.ndarray, out: np.ndarray
    ) -> np.ndarray:
        """:meth:`scores` for binary descriptors (``out``: the no-match distances, filled)."""
        if query.descriptors.dtype != np.uint8 or refs.descriptors.dtype != np.uint8:
            raise ValueError(
                f"descriptor {self.config.descriptor!r}: features must be binary (uint8), got "  # type: ignore[attr-defined]
                f"{query.descriptors.dtype} and {refs.descriptors.dtype}"
            )
        live = np.flatnonzero(refs.counts[idx] > 0)
        if len(live) == 0:
            return out
        nq = query.descriptors.shape[0]
        ssd1, ssd2 = np.empty((len(live), nq)), np.empty((len(live), nq))
        for j, i in enumerate(idx[live]):
            a, b = refs.offsets[i], refs.offsets[i + 1]
            ssd1[j], ssd2[j], _ = hamming_nearest_two(query.descriptors, refs.descriptors[a:b])
        out[live] = self._distance(ssd1, ssd2)
        return out

    @staticmethod
    def _best_two(q: np.ndarray, block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nq, 65) x (m, n_max, 65) -> best and second-best similarity, each (nq, m)."""
        nq, (m, n_max, _) = q.shape[0], block.shape
        sim = (q @ block.reshape(-1, DESC_DIM + 1).T).reshape(nq, m, n_max)
        rows, cols = np.arange(nq)[:, None], np.arange(m)[None, :]
        arg = sim.argmax(axis=2)
        top1 = sim[rows, cols, arg]
        if n_max < 2:
            return top1, np.full_like(top1, -1e9)
        sim[rows, cols, arg] = -np.inf  # remove one maximum; a tied maximum stays
        return top1, sim.max(axis=2)

    def _score_block(
        self,
        q: np.ndarray,
        qn: np.ndarray,
        refs: KazeSet,
        sel: np.ndarray,
        counts: np.ndarray,
        n_max: int,
    ) -> np.ndarray:
        """Distances of the augmented query ``q`` to the references ``sel`` (all non-empty)."""
        slots = np.arange(n_max)[None, :]
        filled = slots < counts[:, None]  # (m, n_max)
        block = np.zeros((len(sel), n_max, DESC_DIM + 1), dtype=np.float32)
        block[..., DESC_DIM] = -1e9
        rows = (refs.offsets[sel][:, None] + slots)[filled]
        block[filled, :DESC_DIM] = refs.descriptors[rows]
        block[filled, DESC_DIM] = -0.5 * refs.sq_norms[rows]
        top1, top2 = self._best_two(q, block)
        # (nq, m) -> one distance per reference; query rows go on the last axis.
        return self._distance(_sim_to_ssd(top1, qn).T, _sim_to_ssd(top2, qn).T)


def _sim_to_ssd(sim: np.ndarray, qn: np.ndarray) -> np.ndarray:
    """(nq, m) augmented similarity ``q.d - |d|^2 / 2`` -> SSD ``|q|^2 - 2 s``; padding
    (similarity <= -1e8) -> inf. ``qn``: (nq,) squared query norms."""
    sim = sim.astype(np.float64)
    return np.where(sim <= -1e8, np.inf, np.maximum(qn[:, None] - 2.0 * sim, 0.0))
