"""Only Look Once (method id 10): masked regional CNN features, mutual matching with IDF.

Spec §2.4 (docs/spec/olo.md). **Encoding** (``encode_feat``): for every channel ``m`` of the mask
map M, ``bw = M_m > min(M_m)``; its 8-connected components, in ``bwlabel`` order (first pixel in
column-major scan), each give a region with the channel's mean activation over the component
and the component's inclusive bounding box. The regions whose mean is at least the 200th
largest are kept (ties may keep more) in (channel, component) order. A region's descriptor is
the feature map F over the *whole bounding box* weighted by the L2-normalised mask values of the
same box (both flattened column-major), L2-normalised when non-zero.

**Similarity** (``compare_two(test = reference, refer = query)``): ``S = T Q^T`` (cosines);
reference region i is a mutual match with its best query region j* when i is also j*'s best
and ``S[i, j*] != 0``; each mutual pair adds ``S[i, j*] * idf(w_i) * idf(w_j*)`` with visual
words w from a vocabulary and ``idf(w) = log10(total_images / word_count[w])`` (computed in
floating point, §8.14); the score is that sum over the number of *reference* regions. Higher is
better; 0 without mutual matches. Comparison is vectorised over a candidate list.

Backbones:

* ``vgg_m_1024`` with the original vocabulary (``vocabulary``: ``word_10000.mat`` with the
  10000 x 512 centres ``C``; ``reverse``: ``reverse_10000.mat`` with ``wordcnt``,
  ``totalimg``): exact, features relu4 and masks relu5 of a 224 x 224 input.
* ``efficientnet_lite0`` (default): features from stage 6 (``s6``, 192-d) and masks from the
  head convolution (``head``, 1280 channels after ReLU6) of a 416 x 416 input, both 13 x 13
  like VGG-M's (recall@1 0.60 alone on Gardens Point day -> night, against 0.19 for stages
  4 / 5 at 208 x 208). Stage 6 ends in a linear projection, so both maps go through a ReLU
  first (``relu: true``), which restores the "activation" meaning the rule assumes. Without a
  vocabulary file, one of
  ``vocabulary_size`` words is fitted by k-means on the reference regions and the word counts
  are the references' document frequencies; both are stored with the index.
* ``efficientnet_lite1`` / ``efficientnet_lite2``: the same layers at 448 x 448 / 480 x 480
  (14 x 14 / 15 x 15 maps: Lite0's 416 scaled by the variants' ImageNet sizes).

Deviation: fewer than 200 regions keeps them all (MATLAB would error, §8.12).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import cv2
import numpy as np
from pydantic import Field

from hmpf.errors import WeightsError
from hmpf.methods.base import LocalMethod
from hmpf.methods.cnn import CnnConfig, CnnMethod, kmeans, nearest
from hmpf.methods.kaze import half
from hmpf.methods.registry import register

DEFAULTS = {
    "vgg_m_1024": ("relu4", "relu5", (224, 224)),
    "efficientnet_lite0": ("s6", "head", (416, 416)),
    # Lite0's 416 scaled to the variants' ImageNet sizes (240 / 224, 260 / 224), in whole
    # stride-32 cells: 14 x 14 and 15 x 15 maps.
    "efficientnet_lite1": ("s6", "head", (448, 448)),
    "efficientnet_lite2": ("s6", "head", (480, 480)),
}


def _components(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-connected components of ``M_m > min(M_m)`` for every channel, in bwlabel order.

    All channels are labelled in one call: their transposes are stacked with a zero row
    between them (so no component crosses channels), and the row-major scan of a transposed
    channel is MATLAB's column-major scan of the channel.

    Returns:
        channel (n,), mean activation (n,), inclusive boxes (n, 4: r0, r1, c0, c1).
    """
    c, h, w = mask.shape
    bw = mask > mask.reshape(c, -1).min(axis=1)[:, None, None]
    tiles = np.zeros((c, w + 1, h), dtype=np.uint8)  # (channel, col, row) + a gap row
    tiles[:, :w] = bw.transpose(0, 2, 1)
    values = np.zeros((c, w + 1, h), dtype=np.float64)
    values[:, :w] = mask.transpose(0, 2, 1)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        tiles.reshape(c * (w + 1), h), connectivity=8
    )
    sums = np.bincount(labels.ravel(), weights=values.ravel(), minlength=n)[1:]
    left, top, width, height, area = (stats[1:, i] for i in range(5))
    channel = top // (w + 1)
    # In a transposed tile, x is the original row and y - tile offset the original column.
    c0 = top - channel * (w + 1)
    boxes = np.stack([left, left + width - 1, c0, c0 + height - 1], axis=1)
    return channel, sums / area, boxes


def encode_regions(feat: np.ndarray, mask: np.ndarray, n_regions: int = 200) -> np.ndarray:
    """OLO ``encode_feat``: (Cf, H, W) features and (Cm, H, W) masks -> (R, Cf) float32 rows.

    Rows are unit vectors (or zero); R is ``n_regions`` normally, more on ties at the
    threshold, fewer when there are fewer components.
    """
    return encode_regions_boxes(feat, mask, n_regions)[0]


def encode_regions_boxes(
    feat: np.ndarray, mask: np.ndarray, n_regions: int = 200
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`encode_regions` and each region's inclusive box on the H x W grid, (R, 4:
    r0, r1, c0, c1) int (what the inspection page draws)."""
    channel, means, boxes = _components(mask)
    if len(means) == 0:
        return np.zeros((0, feat.shape[0]), dtype=np.float32), np.zeros((0, 4), np.int64)
    if len(means) > n_regions:
        thr = np.sort(means)[::-1][n_regions - 1]
        keep = np.flatnonzero(means >= thr)
    else:
        keep = np.arange(len(means))
    # Bounding-box pooling for all kept regions at once: a (R, H, W) weight map holds each
    # region's mask values inside its box (zero outside), L2-normalised; v = W . F.
    _, h, w = mask.shape
    r0, r1, c0, c1 = (boxes[keep, i][:, None, None] for i in range(4))
    rows, cols = np.arange(h)[None, :, None], np.arange(w)[None, None, :]
    inside = (rows >= r0) & (rows <= r1) & (cols >= c0) & (cols <= c1)
    weights = np.where(inside, mask[channel[keep]], 0.0).reshape(len(keep), -1)
    weights /= np.maximum(np.linalg.norm(weights, axis=1, keepdims=True), 1e-30)
    v = weights @ feat.reshape(feat.shape[0], -1).T.astype(np.float64)  # (R, Cf)
    norms = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where(norms > 0, v / np.where(norms > 0, norms, 1.0), v)
    return v.astype(np.float32), boxes[keep].astype(np.int64)


def olo_similarity(
    refs: np.ndarray,
    ref_words: np.ndarray,
    ref_counts: np.ndarray,
    query: np.ndarray,
    query_words: np.ndarray,
    idf: np.ndarray,
) -> np.ndarray:
    """OLO ``compare_two`` of one query against n references, vectorised.

    Args:
        refs: (n, R, D) reference regions (rows past ``ref_counts`` are padding).
        ref_words: (n, R) visual word per reference region.
        ref_counts: (n,) regions per reference (the score's denominator).
        query: (Rq, D) query regions.
        query_words: (Rq,) their words.
        idf: (W,) inverse document frequency per word.

    Returns:
        (n,) float64 scores, higher is better.
    """
    n, r = refs.shape[:2]
    if n == 0 or len(query) == 0 or r == 0:
        return np.zeros(n)
    s = np.matmul(refs, query.T.astype(refs.dtype)).astype(np.float32)  # (n, R, Rq)
    pad = np.arange(r)[None, :] >= ref_counts[:, None]  # (n, R)
    s[pad] = -np.inf
    j_star = s.argmax(axis=2)  # (n, R): best query region per reference region
    i_star = s.argmax(axis=1)  # (n, Rq): best reference region per query region
    best = np.take_along_axis(s, j_star[:, :, None], axis=2)[:, :, 0]
    mutual = np.take_along_axis(i_star, j_star, axis=1) == np.arange(r)[None, :]
    ok = mutual & ~pad & (best != 0)
    val = np.where(ok, best, 0.0) * idf[ref_words] * idf[query_words[j_star]]
    return val.sum(axis=1) / np.maximum(ref_counts, 1)


@dataclass(frozen=True)
class OloFeatures:
    """One image's regions (R, D) float32 (unit rows) and their visual words (R,) int32."""

    regions: np.ndarray
    words: np.ndarray

    def __len__(self) -> int:
        return len(self.regions)


@dataclass(frozen=True)
class OloSet:
    """Reference region sets padded to (N, R, D), with words (N, R) and counts (N,)."""

    regions: np.ndarray
    words: np.ndarray
    counts: np.ndarray

    @classmethod
    def from_features(cls, features: Sequence[OloFeatures], dim: int) -> OloSet:
        r = max((len(f) for f in features), default=0)
        regions = np.zeros((len(features), r, dim), dtype=np.float32)
        words = np.zeros((len(features), r), dtype=np.int32)
        counts = np.zeros(len(features), dtype=np.int64)
        for i, f in enumerate(features):
            regions[i, : len(f)] = f.regions
            words[i, : len(f)] = f.words
            counts[i] = len(f)
        return cls(regions, words, counts)

    def __len__(self) -> int:
        return len(self.counts)

    def __getitem__(self, i: int) -> OloFeatures:
        n = int(self.counts[i])
        return OloFeatures(self.regions[i, :n], self.words[i, :n])


class OloConfig(CnnConfig):
    feature_layer: str | None = None
    mask_layer: str | None = None
    relu: bool | None = Field(None, description="ReLU on both maps; None = per backbone")
    regions: int = Field(200, ge=1)
    vocabulary: str | None = Field(None, description="word_10000.mat (C: W x D centres)")
    reverse: str | None = Field(None, description="reverse_10000.mat (wordcnt, totalimg)")
    vocabulary_size: int = Field(256, ge=2, description="words fitted without a vocabulary")
    seed: int = 0


@register
class Olo(CnnMethod, LocalMethod):
    name = "olo"
    higher_is_better = True
    version = "3"  # 2: float16-precision descriptors; 3: vectorised region pooling
    Config: ClassVar[type[CnnConfig]] = OloConfig

    def __init__(self, config: OloConfig | None = None) -> None:
        super().__init__(config)
        self._state: dict[str, np.ndarray] = {}
        c = self.olo
        if (c.vocabulary is None) != (c.reverse is None):
            raise ValueError("olo: give both vocabulary and reverse files, or neither")

    @property
    def olo(self) -> OloConfig:
        return self.config  # type: ignore[return-value]

    def _default(self) -> tuple[str, str, tuple[int, int]]:
        if self.olo.backbone not in DEFAULTS:
            raise ValueError(f"olo has no default layers for backbone {self.olo.backbone!r}")
        return DEFAULTS[self.olo.backbone]

    def layers(self) -> list[str]:
        d = self._default()
        return [self.olo.feature_layer or d[0], self.olo.mask_layer or d[1]]

    def default_input_size(self) -> tuple[int, int]:
        return self._default()[2]

    @property
    def use_relu(self) -> bool:
        r = self.olo.relu
        return self.olo.backbone.startswith("efficientnet_lite") if r is None else r

    # -- vocabulary ---------------------------------------------------------------------------
    @cached_property
    def _files(self) -> dict[str, np.ndarray]:
        import scipy.io  # scipy takes ~0.6 s to import: loaded on first use

        c = self.olo
        try:
            words = scipy.io.loadmat(c.vocabulary, variable_names=["C"])["C"]
            rev = scipy.io.loadmat(c.reverse, variable_names=["wordcnt", "totalimg"])
        except (OSError, ValueError, KeyError, NotImplementedError) as exc:
            raise WeightsError(
                f"cannot read the OLO vocabulary ({c.vocabulary}, {c.reverse}): {exc}. They are "
                "build_vocabulary/word_10000.mat and reverse_10000.mat of "
                "github.com/scutzetao/IROS2017_OnlyLookOnce"
            ) from None
        return {
            "vocabulary": np.asarray(words, dtype=np.float32),
            "wordcnt": np.asarray(rev["wordcnt"], dtype=np.float64).reshape(-1),
            "totalimg": np.asarray(rev["totalimg"], dtype=np.float64).reshape(()),
        }

    def _vocab(self) -> dict[str, np.ndarray]:
        if self.olo.vocabulary is not None:
            return self._files
        if "vocabulary" not in self._state:
            raise RuntimeError("olo has no vocabulary: run fit_methods on the references first")
        return self._state

    @property
    def idf(self) -> np.ndarray:
        v = self._vocab()
        return np.log10(float(v["totalimg"]) / np.maximum(v["wordcnt"], 1.0))

    def requires_fit(self) -> bool:
        return self.olo.vocabulary is None and "vocabulary" not in self._state

    def state_arrays(self) -> dict[str, np.ndarray]:
        return dict(self._state)

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        missing = {"vocabulary", "wordcnt", "totalimg"} - set(arrays)
        if missing:
            raise ValueError(f"olo state lacks {sorted(missing)}")
        self._state = {k: np.asarray(v) for k, v in arrays.items()}

    def _regions(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        return self.region_boxes(maps)[0]

    def region_boxes(self, maps: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """One image's regions and their boxes on the maps' grid
        (:func:`encode_regions_boxes`)."""
        f_name, m_name = self.layers()
        feat, mask = maps[f_name], maps[m_name]
        if self.use_relu:
            feat, mask = np.maximum(feat, 0), np.maximum(mask, 0)
        return encode_regions_boxes(feat, mask, self.olo.regions)

    def fit_from_maps(self, samples: Sequence[Mapping[str, np.ndarray]]) -> None:
        regions = [self._regions(maps) for maps in samples]
        vocab = kmeans(
            np.concatenate(regions),
            self.olo.vocabulary_size,
            seed=self.olo.seed,
            iters=15,
            max_points=60_000,
        )
        df = np.zeros(len(vocab))
        for r in regions:
            df[np.unique(nearest(r, vocab))] += 1
        self._state = {
            "vocabulary": vocab,
            "wordcnt": df,
            "totalimg": np.array(len(samples), dtype=np.float64),
        }

    # -- features and scores --------------------------------------------------------------------
    def from_maps(self, maps: Mapping[str, np.ndarray]) -> OloFeatures:
        r = half(self._regions(maps))  # float16 precision: what the index stores
        return OloFeatures(r, self.words(r))

    def words(self, regions: np.ndarray) -> np.ndarray:
        """The visual word of each region (R,) int32."""
        return nearest(regions, self._vocab()["vocabulary"]).astype(np.int32)

    def to_arrays(self, feature: OloFeatures) -> dict[str, np.ndarray]:
        return {"regions": feature.regions, "words": feature.words}

    def from_arrays(self, arrays: dict[str, np.ndarray]) -> OloFeatures:
        return OloFeatures(arrays["regions"].astype(np.float32), arrays["words"].astype(np.int32))

    def stack(self, features: Sequence[OloFeatures]) -> OloSet:
        dim = next((f.regions.shape[1] for f in features), 0)
        return OloSet.from_features(features, dim)

    def scores(
        self, query: OloFeatures, references: Any, subset: np.ndarray | None = None
    ) -> np.ndarray:
        refs: OloSet = references
        idx = np.arange(len(refs)) if subset is None else np.asarray(subset, dtype=np.int64)
        out = np.zeros(len(idx))
        idf = self.idf
        chunk = 256  # bounds the (chunk, R, Rq) similarity block
        for s in range(0, len(idx), chunk):
            sel = idx[s : s + chunk]
            out[s : s + chunk] = olo_similarity(
                refs.regions[sel],
                refs.words[sel],
                refs.counts[sel],
                query.regions,
                query.words,
                idf,
            )
        return out
