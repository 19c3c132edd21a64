"""The local-feature evidence between a query image and one reference, drawn as a PNG.

:func:`render_evidence` puts the query (left) beside the reference's stored thumbnail
(right), both scaled to :data:`HEIGHT` pixels, and draws what matched:

* **KAZE** (when the index has a ``kaze`` method): the query's keypoints, extracted from the
  upload, against the reference's keypoints *as stored in the index*; a pair is drawn when
  the two descriptors are each other's nearest neighbours and pass the method's ratio test
  (``max_ratio``); at most :data:`MAX_PAIRS`, closest first, as dots joined by lines.
* **OLO** (otherwise, when the index has an ``olo`` method): the index stores region
  descriptors, not where the regions lie, so both sides are encoded here, the query from
  the upload and the reference from its thumbnail (a 160-pixel image: the reference's regions
  are close to, not exactly, the stored ones); a pair is a mutual best match (OLO's rule),
  weighted by the cosine times both visual words' idf (a box that several mask channels
  share counts once); the :data:`MAX_PAIRS` heaviest pairs
  are drawn as boxes on the 13 x 13 map grid, same colour on both sides, joined by lines.

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
from hmpf.methods.kaze import Kaze, KazeFeatures
from hmpf.methods.olo import Olo

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
        q_boxes, r_boxes = _olo_pairs(method, query, ref_img)
    return Evidence(_draw(query, ref_img, q_boxes, r_boxes), mid, len(q_boxes))


def _points(xy: np.ndarray) -> np.ndarray:
    """Points (n, 2: x, y in [0, 1]) as zero-size boxes (n, 4: x0, y0, x1, y1)."""
    return np.concatenate([xy, xy], axis=1) if len(xy) else np.zeros((0, 4))


def _kaze_pairs(
    method: Kaze, ref: KazeFeatures, query: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint positions (n, 2 each, in the method's image_size frame) of mutual nearest
    descriptor pairs passing the ratio test, closest first."""
    q = method.extract(query)
    if len(q) == 0 or len(ref) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    d = np.maximum(
        2.0 - 2.0 * (q.descriptors.astype(np.float64) @ ref.descriptors.T.astype(np.float64)), 0
    )
    best = d.argmin(axis=1)
    back = d.argmin(axis=0)
    two = np.sort(d, axis=1)[:, :2]
    ratio = float(method.config.max_ratio)  # type: ignore[attr-defined]
    ok = (back[best] == np.arange(len(q))) & (two[:, 0] < (ratio**2) * two[:, 1])
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(d[idx, best[idx]], kind="stable")][:MAX_PAIRS]
    return q.keypoints[idx, :2], ref.keypoints[best[idx], :2]


def _olo_pairs(method: Olo, query: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (n, 4: x0, y0, x1, y1 in [0, 1]) of the heaviest mutual region pairs."""
    (q_maps, r_maps) = list(forward_group([method], [query, ref]))
    q_reg, q_box = _distinct(*method.region_boxes(q_maps))
    r_reg, r_box = _distinct(*method.region_boxes(r_maps))
    if len(q_reg) == 0 or len(r_reg) == 0:
        return np.zeros((0, 4)), np.zeros((0, 4))
    idf = method.idf
    s = r_reg @ q_reg.T
    j_star = s.argmax(axis=1)
    i_star = s.argmax(axis=0)
    mutual = np.flatnonzero((i_star[j_star] == np.arange(len(r_reg))) & (s.max(axis=1) > 0))
    weight = (
        s[mutual, j_star[mutual]]
        * idf[method.words(r_reg[mutual])]
        * idf[method.words(q_reg[j_star[mutual]])]
    )
    top = mutual[np.argsort(-weight, kind="stable")][:MAX_PAIRS]
    grid = next(iter(q_maps.values())).shape[1:]
    return _grid_boxes(q_box[j_star[top]], grid), _grid_boxes(r_box[top], grid)


def _distinct(regions: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first region of each distinct box: masks of several channels often give the same
    component, whose near-identical descriptors would keep each other from being mutual."""
    if len(boxes) == 0:
        return regions, boxes
    first = np.sort(np.unique(boxes, axis=0, return_index=True)[1])
    return regions[first], boxes[first]


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
