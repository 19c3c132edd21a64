"""Reference thumbnails: small JPEGs stored in the index, so that a viewer (the service's
inspection page) can show a reference without the original image folder.

``thumbnails.h5`` (format 1.1; a version built before has none, readers then return None)::

    /jpeg/data      (sum b_i,) uint8   the JPEG files' bytes, one after the other
    /jpeg/offsets   (N + 1,) int64     reference ``i`` owns ``data[offsets[i]:offsets[i + 1]]``

A thumbnail's longest side is :data:`MAX_SIDE` pixels (smaller images are not enlarged),
JPEG quality :data:`QUALITY`: 3.5 KiB per reference for Gardens Point's 960 x 540
frames (160 x 90 thumbnails). An empty entry means "no
thumbnail" (references copied by ``add`` from a version that had none). The file is listed in
the manifest like every other file, so its sha256 is checked with them.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hmpf.imageio import load_image
from hmpf.index.layout import IndexCorruptError
from hmpf.index.tables import Ragged

__all__ = [
    "FILE",
    "MAX_SIDE",
    "QUALITY",
    "ThumbnailStore",
    "empty_thumbnails",
    "make_thumbnail",
    "make_thumbnails",
    "write_thumbnails",
]

FILE = "thumbnails.h5"
MAX_SIDE = 160
QUALITY = 75


def make_thumbnail(image: np.ndarray, max_side: int = MAX_SIDE, quality: int = QUALITY) -> bytes:
    """JPEG bytes of an RGB ``uint8`` image shrunk (area interpolation) to ``max_side``."""
    h, w = image.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise ValueError("JPEG encoding failed")
    return bytes(buf.tobytes())


def _cached_thumbnail(path: Path, cache: Path | None, key: str) -> np.ndarray:
    hit = cache / f"{key}.jpg" if cache is not None and key else None
    if hit is not None and hit.is_file():
        return np.frombuffer(hit.read_bytes(), np.uint8)
    data = make_thumbnail(load_image(path))
    if hit is not None:
        # one temporary file per thread: identical images (one key) may be made at once
        tmp = hit.with_name(f"{key}.{os.getpid()}-{threading.get_ident()}.tmp")
        tmp.write_bytes(data)
        tmp.replace(hit)
    return np.frombuffer(data, np.uint8)


def make_thumbnails(
    paths: Sequence[Path], digests: Sequence[str] = (), cache: Path | None = None
) -> Ragged:
    """Thumbnails of ``paths`` (in order) on a few threads (OpenCV releases the GIL).

    With ``cache`` (a folder) and each image's sha256 in ``digests``, a thumbnail made before
    (an interrupted build) is read from there and new ones are saved there.
    """
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
    keys = list(digests) or [""] * len(paths)
    with ThreadPoolExecutor(4) as pool:
        items = list(pool.map(_cached_thumbnail, paths, [cache] * len(paths), keys))
    return Ragged.from_items(items) if items else empty_thumbnails(0)


def empty_thumbnails(n: int) -> Ragged:
    """``n`` references without a thumbnail."""
    return Ragged(np.zeros(0, np.uint8), np.zeros(n + 1, np.int64))


def write_thumbnails(path: Path, thumbs: Ragged) -> int:
    """Write ``thumbnails.h5``; returns the bytes of the file."""
    import h5py  # the index extra; ~0.2 s to import

    with h5py.File(path, "w", libver="latest") as f:
        g = f.create_group("jpeg")
        g.create_dataset("data", data=np.asarray(thumbs.data, np.uint8))
        g.create_dataset("offsets", data=np.asarray(thumbs.offsets, np.int64))
    return path.stat().st_size


class ThumbnailStore:
    """The thumbnails of an open version (offsets in memory, bytes read on demand)."""

    def __init__(self, f: Any, n: int) -> None:
        self._path = Path(f.filename)
        try:
            self._data = f["jpeg"]["data"]
            self.offsets = np.asarray(f["jpeg"]["offsets"][()], dtype=np.int64)
        except (KeyError, ValueError, OSError) as exc:
            raise IndexCorruptError(f"{self._path}: damaged thumbnails ({exc})") from None
        o = self.offsets
        if len(o) != n + 1 or o[0] != 0 or (np.diff(o) < 0).any() or o[-1] != len(self._data):
            raise IndexCorruptError(f"{self._path}: thumbnail offsets are inconsistent")

    def get(self, i: int) -> bytes | None:
        """Reference ``i``'s JPEG bytes, None when it has no thumbnail."""
        a, b = int(self.offsets[i]), int(self.offsets[i + 1])
        return bytes(self._data[a:b].tobytes()) if b > a else None

    def column(self) -> Ragged:
        """Every reference's thumbnail (for add / remove)."""
        return Ragged(np.asarray(self._data[()], np.uint8), self.offsets.copy())
