"""Input checks done before any work: the image folder, the images' decodability, the CSV.

Metadata CSV: a header row with ``name`` (required: the image file name) and any of the
optional columns ``lat``, ``lon``, ``heading`` (degrees), ``timestamp`` (seconds since the
epoch, or ISO 8601 text) and ``sequence`` (free text, e.g. a route or drive id). Unknown
columns, rows naming no image, duplicate rows and unparsable values are errors. Images
without a row get NaN (empty text for ``sequence``).
"""

from __future__ import annotations

import csv
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from hmpf.datasets import list_images
from hmpf.errors import DatasetError, ImageError
from hmpf.imageio import load_image, probe_image
from hmpf.index.tables import META_COLUMNS, TEXT_COLUMNS

__all__ = [
    "ImageCheck",
    "check_images",
    "read_metadata",
    "scan_images",
]

_RANGES = {"lat": (-90.0, 90.0), "lon": (-180.0, 180.0), "heading": (-360.0, 360.0)}


def scan_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder``, natural-sorted, with distinct names.

    Raises:
        DatasetError: the folder is missing or empty, or two files differ only in case (they
            would collide on case-insensitive file systems and in metadata lookups).
    """
    paths = list_images(folder)
    seen: dict[str, str] = {}
    for p in paths:
        key = p.name.lower()
        if key in seen:
            raise DatasetError(
                f"{folder}: duplicate image names {seen[key]!r} and {p.name!r}; rename one"
            )
        seen[key] = p.name
    return paths


@dataclass
class ImageCheck:
    """What one read of each image file found (:func:`check_images`).

    Attributes:
        digests: per path, in order, the sha256 hex digest of the file's bytes (the format of
            :func:`hmpf.features.file_digest`), or ``"unreadable:<OS error>"`` for a file that
            cannot be read.
        unreadable: the paths :func:`~hmpf.imageio.load_image` cannot read, in order, with
            the error it raises (same reason text as the extraction would give).
    """

    digests: list[str] = field(default_factory=list)
    unreadable: dict[Path, ImageError] = field(default_factory=dict)


def check_images(paths: Sequence[Path]) -> ImageCheck:
    """Read each file of ``paths`` once (one at a time): its digest and whether it decodes.

    The bytes are hashed and given to :func:`~hmpf.imageio.probe_image` (a cheap decode;
    :func:`~hmpf.imageio.load_image`'s error for the failures). A file that cannot be read
    at all gets ``load_image``'s error (``no such file``, the OS error).
    """
    out = ImageCheck()
    for p in paths:
        try:
            data = p.read_bytes()
        except OSError as exc:
            out.digests.append(f"unreadable:{exc.strerror}")
            try:
                load_image(p)
            except ImageError as err:
                out.unreadable[p] = err
            continue
        digest = hashlib.sha256(data).hexdigest()
        out.digests.append(digest)
        reason = probe_image(data, str(p))
        del data
        if reason is not None:
            out.unreadable[p] = ImageError(str(p), reason)
    return out


def _parse_value(col: str, text: str, where: str) -> float | str:
    text = text.strip()
    if col in TEXT_COLUMNS:
        return text
    if text == "":
        return math.nan
    try:
        value = float(text)
    except ValueError:
        if col != "timestamp":
            raise DatasetError(f"{where}: {col} {text!r} is not a number") from None
        try:
            value = datetime.fromisoformat(text).timestamp()
        except ValueError:
            raise DatasetError(
                f"{where}: timestamp {text!r} is neither seconds nor ISO 8601"
            ) from None
    lo_hi = _RANGES.get(col)
    if lo_hi is not None and not (lo_hi[0] <= value <= lo_hi[1]):
        raise DatasetError(f"{where}: {col} {value} is outside [{lo_hi[0]}, {lo_hi[1]}]")
    return value


def read_metadata(path: str | Path, names: Sequence[str]) -> dict[str, np.ndarray]:
    """Metadata columns aligned with ``names`` (see the module docstring).

    Returns:
        column -> (N,) float64 (NaN = missing) or object array of str (``sequence``); only
        the columns the CSV has.

    Raises:
        DatasetError: unreadable file, no ``name`` column, unknown column, duplicate row, a
            row naming no image, or a bad value (the message gives file and line).
    """
    src = str(path)
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in (reader.fieldnames or [])]
            rows = list(reader)
    except OSError as exc:
        raise DatasetError(f"cannot read metadata CSV {src!r}: {exc.strerror or exc}") from None
    if "name" not in header:
        raise DatasetError(
            f"{src}: the header must have a 'name' column (and any of {', '.join(META_COLUMNS)})"
        )
    unknown = [h for h in header if h != "name" and h not in META_COLUMNS]
    if unknown:
        raise DatasetError(
            f"{src}: unknown column(s) {', '.join(unknown)}; allowed: name, "
            + ", ".join(META_COLUMNS)
        )
    cols = [c for c in META_COLUMNS if c in header]
    index = {n: i for i, n in enumerate(names)}
    out = {
        c: (
            np.full(len(names), "", dtype=object)
            if c in TEXT_COLUMNS
            else np.full(len(names), np.nan)
        )
        for c in cols
    }
    seen: set[str] = set()
    orphans: list[str] = []
    for line, raw in enumerate(rows, start=2):
        row = {(k or "").strip(): (v or "") for k, v in raw.items()}
        name = row["name"].strip()
        if not name:
            raise DatasetError(f"{src}:{line}: empty name")
        if name in seen:
            raise DatasetError(f"{src}:{line}: duplicate row for {name!r}")
        seen.add(name)
        if name not in index:
            orphans.append(name)
            continue
        for c in cols:
            out[c][index[name]] = _parse_value(c, row.get(c, ""), f"{src}:{line}")
    if orphans:
        more = f" and {len(orphans) - 5} more" if len(orphans) > 5 else ""
        raise DatasetError(
            f"{src}: {len(orphans)} row(s) name no image in the folder: "
            f"{', '.join(orphans[:5])}{more}"
        )
    return out
