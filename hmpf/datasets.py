"""Image folders and ground truth.

Ground truth is a boolean matrix ``gt[q, r]`` (queries x references): True when reference ``r``
is a correct match for query ``q``. Three forms build it:

* frame alignment: traverses are frame-aligned, ``|q - r| <= tolerance`` (positions in the
  natural-sorted file lists);
* a pairs CSV: rows ``query,reference[,tolerance]``; entries are file names or 1-based
  positions; the optional third column widens the pair to ``reference +- tolerance`` frames
  (the layout of ``nordland_64x32/sample_ground_truth.csv``); an optional header row
  ``query,reference[,tolerance]`` is skipped;
* a GPS CSV with header ``role,name,lat,lon`` (role ``reference`` or ``query``): pairs closer
  than a radius in metres (haversine, R = 6378.137 km as the original's ``GPS2Meters``).
"""

from __future__ import annotations

import csv
import os
import re
from pathlib import Path

import numpy as np

from hmpf.errors import DatasetError
from hmpf.imageio import IMAGE_EXTENSIONS

__all__ = [
    "dataset_root",
    "frame_ground_truth",
    "gps_ground_truth",
    "list_images",
    "natural_key",
    "pairs_ground_truth",
]

EARTH_RADIUS_M = 6_378_137.0

#: The Gardens Point Walking protocols the benchmarks and reports use: name -> (reference
#: folder, query folder), relative to :func:`dataset_root`; frame-aligned (+-N frames).
GARDENS_POINT_PROTOCOLS = {
    "gp_dr_nr": ("gardens_point/day_right", "gardens_point/night_right"),
    "gp_dl_nr": ("gardens_point/day_left", "gardens_point/night_right"),
    "gp_dl_dr": ("gardens_point/day_left", "gardens_point/day_right"),
}


def dataset_root() -> Path:
    """Folder holding the shared datasets: ``$HMPF_DATASETS`` or ``../shared/datasets``."""
    env = os.environ.get("HMPF_DATASETS")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parent.parent
    return (here.parent / "shared" / "datasets").resolve()


def natural_key(name: str) -> list[object]:
    """Sort key comparing digit runs numerically (MATLAB ``sort_nat``)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: str | os.PathLike[str]) -> list[Path]:
    """Image files of ``folder`` (by extension), natural-sorted.

    Raises:
        DatasetError: the folder does not exist or holds no image.
    """
    p = Path(folder)
    if not p.is_dir():
        raise DatasetError(f"image folder {str(p)!r} does not exist")
    files = [f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_EXTENSIONS]
    if not files:
        raise DatasetError(
            f"image folder {str(p)!r} holds no image ({', '.join(IMAGE_EXTENSIONS)})"
        )
    return sorted(files, key=lambda f: natural_key(f.name))


def frame_ground_truth(n_query: int, n_ref: int, tolerance: int) -> np.ndarray:
    """``gt[q, r] = |q - r| <= tolerance`` for frame-aligned traverses."""
    if tolerance < 0:
        raise DatasetError("tolerance must be >= 0 frames")
    q = np.arange(n_query)[:, None]
    r = np.arange(n_ref)[None, :]
    return np.abs(q - r) <= tolerance


def _resolve(token: str, names: list[str], what: str, source: str, line: int) -> int:
    token = token.strip()
    lookup = {n: i for i, n in enumerate(names)}
    if token in lookup:
        return lookup[token]
    if token.isdigit():
        idx = int(token) - 1
        if 0 <= idx < len(names):
            return idx
        raise DatasetError(f"{source}:{line}: {what} position {token} is out of 1..{len(names)}")
    raise DatasetError(f"{source}:{line}: {what} {token!r} is neither a file name nor a position")


def pairs_ground_truth(
    path: str | os.PathLike[str], query_names: list[str], ref_names: list[str]
) -> np.ndarray:
    """Ground truth from a pairs CSV (see module docstring)."""
    gt = np.zeros((len(query_names), len(ref_names)), dtype=bool)
    src = str(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise DatasetError(f"cannot read ground-truth CSV {src!r}: {exc.strerror}") from None
    for n, row in enumerate(rows, start=1):
        if not row or all(not c.strip() for c in row):
            continue
        if n == 1 and row[0].strip().lower() == "query":
            continue
        if len(row) not in (2, 3):
            raise DatasetError(f"{src}:{n}: expected query,reference[,tolerance]")
        qi = _resolve(row[0], query_names, "query", src, n)
        ri = _resolve(row[1], ref_names, "reference", src, n)
        tol = 0
        if len(row) == 3:
            try:
                tol = int(row[2])
            except ValueError:
                raise DatasetError(f"{src}:{n}: tolerance {row[2]!r} is not an integer") from None
        gt[qi, max(0, ri - tol) : ri + tol + 1] = True
    if not gt.any():
        raise DatasetError(f"{src}: no ground-truth pair")
    return gt


def haversine_m(
    lat1: float | np.ndarray,
    lon1: float | np.ndarray,
    lat2: float | np.ndarray,
    lon2: float | np.ndarray,
) -> np.ndarray:
    """Great-circle distance in metres (broadcasting)."""
    p1, p2 = np.radians(lat1), np.radians(lat2)
    dphi = p2 - p1
    dl = np.radians(lon2) - np.radians(lon1)
    a = np.sin(dphi / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(a, 0, 1)))


def gps_ground_truth(
    path: str | os.PathLike[str],
    query_names: list[str],
    ref_names: list[str],
    radius_m: float,
) -> np.ndarray:
    """Ground truth from a ``role,name,lat,lon`` CSV: pairs within ``radius_m`` metres."""
    src = str(path)
    pos = {"reference": {}, "query": {}}  # type: dict[str, dict[str, tuple[float, float]]]
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            need = {"role", "name", "lat", "lon"}
            if reader.fieldnames is None or not need <= set(reader.fieldnames):
                raise DatasetError(f"{src}: header must contain role,name,lat,lon")
            for n, row in enumerate(reader, start=2):
                role = row["role"].strip()
                if role not in pos:
                    raise DatasetError(f"{src}:{n}: role must be 'reference' or 'query'")
                try:
                    pos[role][row["name"].strip()] = (float(row["lat"]), float(row["lon"]))
                except ValueError:
                    raise DatasetError(f"{src}:{n}: lat/lon must be numbers") from None
    except OSError as exc:
        raise DatasetError(f"cannot read GPS CSV {src!r}: {exc.strerror}") from None

    def coords(role: str, names: list[str]) -> np.ndarray:
        missing = [n for n in names if n not in pos[role]]
        if missing:
            raise DatasetError(f"{src}: no {role} position for {', '.join(missing[:5])}")
        return np.array([pos[role][n] for n in names])

    q = coords("query", query_names)
    r = coords("reference", ref_names)
    d = haversine_m(q[:, None, 0], q[:, None, 1], r[None, :, 0], r[None, :, 1])
    return d <= radius_m
