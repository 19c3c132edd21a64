"""Pseudo-queries: query/place pairs with known truth, made from the references alone.

An operator who has mapped a route has its references (images, their order along the route,
often GPS) but no query with a known place. The references carry their own supervision:

* **Where an image is.** Route order is file order, or the ``sequence`` (one route per value)
  and ``timestamp`` metadata when given (:class:`~hmpf.sequence.RouteMap`, as the index orders
  its references); with ``lat``/``lon`` for every sampled reference, GPS positions.
* **What a later drive sees there.** A pseudo-query is a reference image changed the way a
  camera's view of a place changes between drives (:class:`Transform`): exposure, gamma, a
  night-like darkening with sensor noise, blur, a small shift and crop of the view (a camera a
  little off the first drive's line, or a frame taken a little earlier or later), a lower
  resolution.

**What "right" means.** The pseudo-query made from reference ``i`` is answered against the map
with reference ``i`` itself masked out: it is never a match, and in the score banks it is no
candidate (:func:`hmpf.evaluation.auto.mask_sources`). An answer is right when it lies within
``+-tolerance`` positions of ``i`` along ``i``'s route (another reference, never ``i``), or,
with GPS, within ``radius_m`` metres of ``i``.

**Why this predicts real queries.** A real query never lands on the very image stored in the
map: it is taken on another drive, between or beside the stored frames, under other light.
Finding ``i`` itself from a changed copy of ``i`` would measure only robustness to the
photometric change, and every method scores near-perfectly on it (the same pixels are
there). Masking ``i`` asks for what a real query asks: the *neighbouring* frames, which show
the same place from a few metres away (another viewpoint, other occlusions), under a changed
appearance. A method (or a hierarchy) that ranks adjacent frames of a place first under those
changes is the one that ranks a new drive's frames first. What pseudo-queries cannot imitate
is a change the references never show (snow on a summer route, a new building): they rank
hierarchies by how well they recognise a place across viewpoint and photometric change, and
``bench/auto_config.py`` measures how well that ranking agrees with real queries' (rank
correlation per route).

**Bounded.** At most ``max_references`` references are looked at (stretches of consecutive
references spread along the routes, :func:`plan`), and at most ``max_queries`` pseudo-queries
are made from them. Everything is deterministic for a seed: the stretches' offsets, which
references become pseudo-queries and each pseudo-query's changes (drawn from
``(seed, reference index, copy)``, so a pseudo-query does not depend on the others).

**Held out from fitting.** Along each route, stretches of ``block`` positions take turns:
``fit`` (methods with fitted parameters, such as NetVLAD's centroids or a whitening, are
fitted on these references only), ``search`` (pseudo-queries the search ranks hierarchies on)
and ``check`` (pseudo-queries held out from the search too, on which the choice is
confirmed): fit, search, fit, check, ... Every sampled reference, of any role, is in the map
the pseudo-queries are answered against, as every reference is in a built index.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hmpf.datasets import haversine_m
from hmpf.errors import DatasetError
from hmpf.sequence import RouteMap

__all__ = [
    "ROLES",
    "PseudoPlan",
    "RoutePositions",
    "Transform",
    "draw_transform",
    "plan",
    "pseudo_truth",
    "read_metadata_csv",
    "route_positions",
    "sample_stretches",
]

#: A sampled reference's role (see the module docstring), in the order the stretches take.
ROLES = ("fit", "search", "fit", "check")


# -- the changes a camera sees between drives --------------------------------------------------


@dataclass(frozen=True)
class Transform:
    """The changes that make one pseudo-query from a reference image (identity by default).

    Attributes:
        gain: exposure, multiplies the intensities (1: unchanged).
        gamma: ``out = in ** gamma`` on [0, 1] intensities (> 1 darker mid-tones).
        night: a night-like darkening: the image scaled by this factor (< 1), a bluish cast
            and shadows crushed (``gamma 1.5``); 1: none.
        noise: sensor noise, standard deviation in 8-bit levels (after darkening).
        blur: Gaussian blur, sigma as a fraction of the shorter side (0: none).
        crop: the view kept, as a fraction of each side (1: all of it); resized back.
        shift_x, shift_y: where the kept view sits, from -1 (left / top) to 1.
        resolution: the image is resampled to this fraction of its size and back (1: none).
        noise_seed: the noise's seed.
    """

    gain: float = 1.0
    gamma: float = 1.0
    night: float = 1.0
    noise: float = 0.0
    blur: float = 0.0
    crop: float = 1.0
    shift_x: float = 0.0
    shift_y: float = 0.0
    resolution: float = 1.0
    noise_seed: int = 0

    def apply(self, image: np.ndarray) -> np.ndarray:
        """The changed image, H x W x 3 ``uint8`` of the input's size."""
        img = np.asarray(image)
        h, w = img.shape[:2]
        out = _view(img, self.crop, self.shift_x, self.shift_y)
        if self.resolution < 1.0:
            small = (max(2, round(w * self.resolution)), max(2, round(h * self.resolution)))
            out = cv2.resize(out, small, interpolation=cv2.INTER_AREA)
            out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
        x = out.astype(np.float32) / 255.0
        x = np.clip(x * self.gain, 0.0, 1.0)
        if self.gamma != 1.0:
            x = np.power(x, self.gamma)
        if self.night < 1.0:
            x = self.night * np.power(x, 1.5)
            x = x * np.array([0.8, 0.9, 1.1], np.float32)  # RGB: a bluish cast
        if self.blur > 0.0:
            sigma = max(0.5, self.blur * min(h, w))
            x = cv2.GaussianBlur(x, (0, 0), sigmaX=sigma, sigmaY=sigma)
        if self.noise > 0.0:
            rng = np.random.default_rng(self.noise_seed)
            x = x + rng.normal(0.0, self.noise / 255.0, x.shape).astype(np.float32)
        return np.ascontiguousarray(np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8))

    def describe(self) -> str:
        """``gain 1.3, blur 0.004, crop 0.9 (+0.2, -0.5)``: the changes that differ from none."""
        parts = []
        for name, value, none in (
            ("gain", self.gain, 1.0),
            ("gamma", self.gamma, 1.0),
            ("night", self.night, 1.0),
            ("noise", self.noise, 0.0),
            ("blur", self.blur, 0.0),
            ("resolution", self.resolution, 1.0),
        ):
            if value != none:
                parts.append(f"{name} {value:.3g}")
        if self.crop != 1.0:
            parts.append(f"crop {self.crop:.3g} ({self.shift_x:+.2f}, {self.shift_y:+.2f})")
        return ", ".join(parts) or "none"

    def to_dict(self) -> dict[str, float | int]:
        return asdict(self)


def _view(img: np.ndarray, crop: float, sx: float, sy: float) -> np.ndarray:
    """The ``crop`` share of each side at (``sx``, ``sy``) in [-1, 1], resized back."""
    if crop >= 1.0:
        return img
    h, w = img.shape[:2]
    cw, ch = max(2, round(w * crop)), max(2, round(h * crop))
    x0 = round((w - cw) * (sx + 1.0) / 2.0)
    y0 = round((h - ch) * (sy + 1.0) / 2.0)
    part = img[y0 : y0 + ch, x0 : x0 + cw]
    return cv2.resize(part, (w, h), interpolation=cv2.INTER_LINEAR)


def draw_transform(rng: np.random.Generator) -> Transform:
    """One pseudo-query's changes: always one change of light (exposure, gamma or night) and
    of view (a shift and crop), and each of blur and a lower resolution with probability
    0.4 and 0.3. The ranges are those of two drives of one camera: exposure x0.5 to x1.6,
    gamma 0.6 to 1.7, night at 15-40 % of the light with noise, a view 80-95 % of each side
    anywhere in the frame, blur up to 0.8 % of the shorter side, resolution down to 35 %."""
    light = int(rng.integers(3))
    gain, gamma, night, noise = 1.0, 1.0, 1.0, 0.0
    if light == 0:
        gain = float(math.exp(rng.uniform(math.log(0.5), math.log(1.6))))
    elif light == 1:
        gamma = float(math.exp(rng.uniform(math.log(0.6), math.log(1.7))))
    else:
        night = float(rng.uniform(0.15, 0.4))
        noise = float(rng.uniform(2.0, 8.0))
    crop = float(rng.uniform(0.8, 0.95))
    sx, sy = (float(v) for v in rng.uniform(-1.0, 1.0, 2))
    blur = float(rng.uniform(0.002, 0.008)) if rng.random() < 0.4 else 0.0
    resolution = float(rng.uniform(0.35, 0.7)) if rng.random() < 0.3 else 1.0
    if noise == 0.0 and rng.random() < 0.3:
        noise = float(rng.uniform(1.0, 4.0))
    return Transform(
        gain=round(gain, 4),
        gamma=round(gamma, 4),
        night=round(night, 4),
        noise=round(noise, 3),
        blur=round(blur, 5),
        crop=round(crop, 4),
        shift_x=round(sx, 3),
        shift_y=round(sy, 3),
        resolution=round(resolution, 4),
        noise_seed=int(rng.integers(2**31)),
    )


# -- where each reference is -------------------------------------------------------------------


@dataclass(frozen=True)
class RoutePositions:
    """Each reference's route and position along it (from :func:`route_positions`).

    Attributes:
        routes: the :class:`~hmpf.sequence.RouteMap` of every reference.
        lat, lon: (N,) degrees, or None without GPS.
    """

    routes: RouteMap
    lat: np.ndarray | None = None
    lon: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.routes.n

    @property
    def position(self) -> np.ndarray:
        """(N,) each reference's position along its own route (0 at its start)."""
        r = self.routes
        return r.rank - r.route_start[r.route_of]


def route_positions(n: int, metadata: Mapping[str, Any] | None = None) -> RoutePositions:
    """Where the ``n`` references are, from metadata columns aligned with them (as the
    indexer reads them: ``sequence``, ``timestamp``, ``lat``, ``lon``; others are ignored).
    Without metadata: one route in file order."""
    meta = dict(metadata or {})
    for col, values in meta.items():
        if values is not None and len(values) != n:
            raise DatasetError(f"metadata column {col!r} has {len(values)} values for {n} images")
    ts = meta.get("timestamp")
    routes = RouteMap.from_metadata(
        n,
        sequence=meta.get("sequence"),
        timestamp=None if ts is None else np.asarray(ts, np.float64),
    )
    lat, lon = meta.get("lat"), meta.get("lon")
    if lat is None or lon is None:
        return RoutePositions(routes)
    return RoutePositions(routes, np.asarray(lat, np.float64), np.asarray(lon, np.float64))


# -- the plan: which references, which pseudo-queries, their truth ----------------------------


def sample_stretches(
    routes: RouteMap, max_references: int, stretch: int, seed: int = 0
) -> np.ndarray:
    """At most ``max_references`` references as stretches of ``stretch`` consecutive ones
    spread evenly along the routes (route after route), in route order; all of them when
    there are no more. The seed shifts the stretches within their share of the routes."""
    n = routes.n
    if max_references < 1 or stretch < 1:
        raise ValueError("max_references and stretch must be >= 1")
    if n <= max_references:
        return routes.ordered.copy()
    stretch = min(stretch, max_references)
    count = max_references // stretch
    share = n / count  # of the route-ordered list, per stretch
    rng = np.random.default_rng([seed, n, max_references, stretch])
    slack = max(0, int(share) - stretch)
    offset = int(rng.integers(slack + 1)) if slack else 0
    starts = (np.floor(np.arange(count) * share).astype(np.int64) + offset).clip(0, n - stretch)
    pos = np.unique((starts[:, None] + np.arange(stretch)[None, :]).ravel())
    return routes.ordered[pos]


def pseudo_truth(
    where: RoutePositions,
    db: np.ndarray,
    sources: np.ndarray,
    *,
    tolerance: int = 2,
    radius_m: float | None = None,
) -> np.ndarray:
    """(Q, len(db)) which map references are right for the pseudo-query of each source.

    ``db`` and ``sources`` are reference indices (each source is in ``db``). Right: on the
    source's route within ``+-tolerance`` positions, or, with ``radius_m`` and GPS for every
    reference of ``db``, within ``radius_m`` metres; never the source itself.
    """
    db = np.asarray(db, np.int64)
    sources = np.asarray(sources, np.int64)
    use_gps = (
        radius_m is not None
        and where.lat is not None
        and where.lon is not None
        and bool(np.isfinite(where.lat[db]).all() and np.isfinite(where.lon[db]).all())
    )
    if use_gps:
        assert where.lat is not None and where.lon is not None and radius_m is not None
        d = haversine_m(
            where.lat[sources][:, None],
            where.lon[sources][:, None],
            where.lat[db][None, :],
            where.lon[db][None, :],
        )
        gt = np.asarray(d <= radius_m, bool)
    else:
        route, pos = where.routes.route_of, where.position
        same = route[sources][:, None] == route[db][None, :]
        near = np.abs(pos[sources][:, None] - pos[db][None, :]) <= tolerance
        gt = same & near
    gt &= sources[:, None] != db[None, :]
    return gt


@dataclass
class PseudoPlan:
    """Which references a choice looks at and the pseudo-queries made from them (:func:`plan`).

    Attributes:
        db: (D,) the references of the map, in route order (reference indices).
        role: (D,) each one's role, one of :data:`ROLES`' names.
        sources: (Q,) the column of ``db`` each pseudo-query was made from.
        part: (Q,) ``search`` or ``check``.
        transforms: (Q,) each pseudo-query's changes.
        gt: (Q, D) which references of the map are right (:func:`pseudo_truth`); a source's
            own column is always False.
        truth: what "right" means, in words.
        n_references: the references there were.
    """

    db: np.ndarray
    role: np.ndarray
    sources: np.ndarray
    part: np.ndarray
    transforms: list[Transform]
    gt: np.ndarray
    truth: str
    n_references: int

    @property
    def fit(self) -> np.ndarray:
        """The reference indices methods are fitted on (role ``fit``)."""
        return self.db[self.role == "fit"]

    def queries(self, part: str) -> np.ndarray:
        """The pseudo-query indices of one part (``search`` or ``check``)."""
        return np.flatnonzero(self.part == part)

    def summary(self) -> dict[str, Any]:
        """The sample sizes, for a report."""
        src_ref = self.db[self.sources]
        return {
            "references": self.n_references,
            "map": int(len(self.db)),
            "fit": int((self.role == "fit").sum()),
            "sources": int(len(np.unique(src_ref))),
            "pseudo_queries": int(len(self.sources)),
            "search": int((self.part == "search").sum()),
            "check": int((self.part == "check").sum()),
            "truth": self.truth,
        }


def plan(
    where: RoutePositions,
    *,
    seed: int = 0,
    max_references: int = 1000,
    max_queries: int = 400,
    min_queries: int = 200,
    max_copies: int = 4,
    stretch: int = 50,
    block: int = 5,
    tolerance: int = 2,
    radius_m: float | None = None,
) -> PseudoPlan:
    """The references to look at and the pseudo-queries to make (see the module docstring).

    Args:
        max_references: the map's size at most (stretches of ``stretch`` references).
        max_queries: pseudo-queries at most (``search`` and ``check`` together).
        min_queries: on a small map, each source gives several pseudo-queries (each with
            its own changes, at most ``max_copies``) until there are this many.
        block: positions per stretch of one role along a route (fit, search, fit, check).
        tolerance, radius_m: what is right (:func:`pseudo_truth`).
    """
    if block < 1 or max_queries < 2 or max_copies < 1:
        raise ValueError("block, max_copies must be >= 1 and max_queries >= 2")
    db = sample_stretches(where.routes, max_references, stretch, seed)
    pos = where.position[db]
    role = np.array([ROLES[int(b)] for b in (pos // block) % len(ROLES)], dtype=object)
    gt_all = pseudo_truth(where, db, db, tolerance=tolerance, radius_m=radius_m)
    usable = gt_all.any(axis=1)  # a source with no right reference in the map is no test
    picked: list[tuple[int, str]] = []
    for part in ("search", "check"):
        cols = np.flatnonzero((role == part) & usable)
        picked += [(int(c), part) for c in cols]
    if len(picked) < 2:
        raise DatasetError(
            f"too few references to make pseudo-queries from ({where.n} references; "
            f"{2 * len(ROLES) * block} along a route always suffice)"
        )
    copies = int(min(max_copies, max(1, math.ceil(min_queries / len(picked)))))
    if len(picked) * copies > max_queries:
        keep = max(2, max_queries // copies)
        idx = np.unique(np.linspace(0, len(picked) - 1, keep).round().astype(np.int64))
        picked = [picked[int(i)] for i in idx]
    sources, parts, transforms = [], [], []
    for col, part in picked:
        ref = int(db[col])
        for c in range(copies):
            sources.append(col)
            parts.append(part)
            transforms.append(draw_transform(np.random.default_rng([seed, ref, c])))
    src = np.asarray(sources, np.int64)
    gps = (
        radius_m is not None
        and where.lat is not None
        and where.lon is not None
        and bool(np.isfinite(where.lat[db]).all() and np.isfinite(where.lon[db]).all())
    )
    truth = (
        f"GPS within {radius_m:g} m of the source reference, which is masked"
        if gps
        else f"within +-{tolerance} positions of the source reference along its route, "
        "which is masked"
    )
    return PseudoPlan(
        db=db,
        role=role,
        sources=src,
        part=np.asarray(parts, dtype=object),
        transforms=transforms,
        gt=gt_all[src],
        truth=truth,
        n_references=where.n,
    )


def read_metadata_csv(path: str | Path, names: Sequence[str]) -> dict[str, np.ndarray]:
    """The route columns of a metadata CSV (the indexer's format: a ``name`` column, any of
    ``lat``, ``lon``, ``heading``, ``timestamp`` (seconds or ISO 8601), ``sequence``),
    aligned with the image ``names``; images without a row get NaN (empty ``sequence``).
    Only what :func:`route_positions` reads is kept; ``hmpf-index build`` checks the file in
    full."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise DatasetError(f"cannot read metadata CSV {str(path)!r}: {exc}") from None
    index = {n: i for i, n in enumerate(names)}
    cols = {"lat", "lon", "timestamp", "sequence"}
    present = {c for row in rows for c, v in row.items() if c in cols and (v or "").strip()}
    if rows and "name" not in rows[0]:
        raise DatasetError(f"{path}: the header must have a 'name' column")
    out: dict[str, np.ndarray] = {
        c: np.full(len(names), "", dtype=object) if c == "sequence" else np.full(len(names), np.nan)
        for c in sorted(present)
    }
    for line, row in enumerate(rows, start=2):
        i = index.get((row.get("name") or "").strip())
        if i is None:
            continue
        for c in present:
            text = (row.get(c) or "").strip()
            if not text:
                continue
            if c == "sequence":
                out[c][i] = text
                continue
            try:
                out[c][i] = float(text)
            except ValueError:
                try:
                    if c != "timestamp":
                        raise
                    out[c][i] = datetime.fromisoformat(text).timestamp()
                except ValueError:
                    raise DatasetError(f"{path}:{line}: {c} {text!r} is not a number") from None
    return out
