"""The local-feature evidence between a query image and one reference, drawn as a PNG.

:func:`render_evidence` puts the query (left) beside the reference's stored thumbnail
(right), both scaled to :data:`HEIGHT` pixels, and draws what matched:

* **KAZE** (when the index has a ``kaze`` method): the query's keypoints, extracted from the
  upload, against the reference's keypoints *as stored in the index*: the matches KAZE's
  distance counts (nearest descriptor within the match threshold, passing the ratio test;
  the ``n_best`` closest, at most :data:`MAX_PAIRS`), as dots joined by lines.
* **OLO** (otherwise, when the index has an ``olo`` method): the pairs OLO's score counts,
  mutual best matches between the query's regions (encoded from the upload) and the
  reference's regions *as stored in the index*, weighted by the cosine times both visual
  words' idf; the :data:`MAX_PAIRS` heaviest are drawn as boxes on the 13 x 13 map grid, same
  colour on both sides, joined by lines. The index stores no boxes, so a stored region is
  drawn at the box of the most similar region encoded from the reference's thumbnail (close
  to where it lies, not exact).

Both methods stretch the whole image to a square input, so grid cells and keypoint
coordinates scale linearly to the drawn images.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np

from hmpf.imageio import decode_image
from hmpf.index.reader import IndexReader
from hmpf.methods.cnn import forward_group
from hmpf.methods.kaze import (
    Kaze,
    KazeBaseConfig,
    KazeFeatures,
    best_two_ssd,
    half,
    hamming_nearest_two,
)
from hmpf.methods.olo import Olo, OloFeatures

__all__ = ["HEIGHT", "MAX_PAIRS", "Evidence", "evidence_method", "render_evidence"]

#: Height of both drawn images, pixels.
HEIGHT = 320
#: Most pairs drawn.
MAX_PAIRS = 24


@dataclass(frozen=True)
class Evidence:
    """A rendered evidence image: PNG bytes, the method drawn and how many pairs."""

    png: bytes
    method: str
    pairs: int


def evidence_method(reader: IndexReader) -> str | None:
    """The id of the local method the evidence is drawn with (KAZE first), None without."""
    for kind in (Kaze, Olo):
        for mid, m in reader.methods.items():
            if isinstance(m, kind):
                return mid
    return None


def render_evidence(reader: IndexReader, query: np.ndarray, ref: int, thumb: bytes) -> Evidence:
    """The evidence between ``query`` (RGB ``uint8``) and reference ``ref`` (its thumbnail's
    JPEG bytes ``thumb``); the caller has checked :func:`evidence_method` is not None."""
    mid = evidence_method(reader)
    assert mid is not None
    method = reader.methods[mid]
    ref_img = decode_image(thumb, "thumbnail")
    if isinstance(method, Kaze):
        q_pts, r_pts = _kaze_pairs(method, reader.local_features(mid, np.array([ref]))[0], query)
        size = float(method.config.image_size)  # type: ignore[attr-defined]
        q_boxes = _points(q_pts / size)
        r_boxes = _points(r_pts / size)
    else:
        assert isinstance(method, Olo)
        stored = reader.local_features(mid, np.array([ref]))[0]
        q_boxes, r_boxes = _olo_pairs(method, stored, query, ref_img)
    return Evidence(_draw(query, ref_img, q_boxes, r_boxes), mid, len(q_boxes))


def _points(xy: np.ndarray) -> np.ndarray:
    """Points (n, 2: x, y in [0, 1]) as zero-size boxes (n, 4: x0, y0, x1, y1)."""
    return np.concatenate([xy, xy], axis=1) if len(xy) else np.zeros((0, 4))


def _kaze_pairs(
    method: Kaze, ref: KazeFeatures, query: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint positions (n, 2 each, in the method's image_size frame) of the matches KAZE's
    distance counts (:func:`~hmpf.methods.kaze.match_distance`: nearest SSD within the match
    threshold and passing the ratio test, the ``n_best`` closest), closest first (``inliers``,
    a KAZE method without ``n_best``: the closest :data:`MAX_PAIRS`)."""
    c = method.config
    assert isinstance(c, KazeBaseConfig)
    q = method.extract(query)
    if len(q) == 0 or len(ref) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    binary = q.descriptors.dtype == np.uint8  # descriptor: beblid / teblid / orb
    if binary:
        ssd1, ssd2, nearest_of = hamming_nearest_two(q.descriptors, ref.descriptors)
    else:
        ssd1, ssd2 = best_two_ssd(q.descriptors, ref.descriptors)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = (ssd1 <= 4.0 * c.match_threshold / 100.0) & (ssd1 / ssd2 <= c.max_ratio)
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(ssd1[idx], kind="stable")][
        : min(MAX_PAIRS, getattr(c, "n_best", MAX_PAIRS))
    ]
    if binary:
        nearest = nearest_of[idx]
    else:
        nearest = (q.descriptors[idx] @ ref.descriptors.T).argmax(axis=1)  # unit rows: least SSD
    return q.keypoints[idx, :2], ref.keypoints[nearest, :2]


def _olo_pairs(
    method: Olo, stored: OloFeatures, query: np.ndarray, thumb: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (n, 4: x0, y0, x1, y1 in [0, 1]) of the heaviest region pairs OLO's score
    counts: mutual best matches between the query's regions and the reference's stored ones,
    weighted by cosine x idf x idf. A stored region's box is that of the most similar region
    encoded from the thumbnail (the index keeps no boxes)."""
    q_maps, t_maps = list(forward_group([method], [query, thumb]))
    q_reg, q_box = method.region_boxes(q_maps)
    t_reg, t_box = method.region_boxes(t_maps)
    refs = stored.regions
    if len(q_reg) == 0 or len(refs) == 0 or len(t_reg) == 0:
        return np.zeros((0, 4)), np.zeros((0, 4))
    q_reg = half(q_reg)  # as the query's feature is scored
    s = refs @ q_reg.T
    j_star = s.argmax(axis=1)
    i_star = s.argmax(axis=0)
    idx = np.flatnonzero((i_star[j_star] == np.arange(len(refs))) & (s.max(axis=1) != 0))
    idf = method.idf
    weight = s[idx, j_star[idx]] * idf[stored.words[idx]] * idf[method.words(q_reg[j_star[idx]])]
    top = idx[np.argsort(-weight, kind="stable")][:MAX_PAIRS]
    where = (t_reg @ refs[top].T).argmax(axis=0)  # the thumbnail region nearest each one
    grid = next(iter(q_maps.values())).shape[1:]
    return _grid_boxes(q_box[j_star[top]], grid), _grid_boxes(t_box[where], grid)


def _grid_boxes(boxes: np.ndarray, grid: tuple[int, ...]) -> np.ndarray:
    """Inclusive grid boxes (r0, r1, c0, c1) as (x0, y0, x1, y1) fractions of the image."""
    h, w = grid
    r0, r1, c0, c1 = (boxes[:, i].astype(np.float64) for i in range(4))
    return np.stack([c0 / w, r0 / h, (c1 + 1) / w, (r1 + 1) / h], axis=1)


def _colour(i: int, n: int) -> tuple[int, int, int]:
    r, g, b = colorsys.hsv_to_rgb(i / max(n, 1), 0.9, 1.0)
    return int(r * 255), int(g * 255), int(b * 255)


def _draw(query: np.ndarray, ref: np.ndarray, q_boxes: np.ndarray, r_boxes: np.ndarray) -> bytes:
    """Query and reference side by side at :data:`HEIGHT`, pairs drawn; PNG bytes."""

    def scaled(img: np.ndarray) -> np.ndarray:
        w = max(1, round(img.shape[1] * HEIGHT / img.shape[0]))
        return cv2.resize(img, (w, HEIGHT), interpolation=cv2.INTER_AREA)

    left, right = scaled(query), scaled(ref)
    gap = 8
    canvas = np.full((HEIGHT, left.shape[1] + gap + right.shape[1], 3), 255, np.uint8)
    canvas[:, : left.shape[1]] = left
    off = left.shape[1] + gap
    canvas[:, off:] = right
    n = len(q_boxes)
    for i, (qb, rb) in enumerate(zip(q_boxes, r_boxes, strict=True)):
        c = _colour(i, n)
        centres = []
        for box, x_off, width in ((qb, 0, left.shape[1]), (rb, off, right.shape[1])):
            x0, y0, x1, y1 = box
            p0 = (x_off + int(x0 * width), int(y0 * HEIGHT))
            p1 = (x_off + int(x1 * width) - 1, int(y1 * HEIGHT) - 1)
            if p1[0] > p0[0] and p1[1] > p0[1]:
                cv2.rectangle(canvas, p0, p1, c, 2)
            else:
                cv2.circle(canvas, p0, 4, c, 2)
            centres.append(((p0[0] + p1[0]) // 2, (p0[1] + p1[1]) // 2))
        cv2.line(canvas, centres[0], centres[1], c, 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
    assert ok
    return bytes(buf.tobytes())
