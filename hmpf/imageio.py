"""Image input: decode from a path or from bytes into an RGB ``uint8`` array.

Every failure (missing, empty, truncated or non-image data) raises :class:`hmpf.errors.ImageError`
naming the source, never a raw OpenCV error. :func:`probe_image` tells, more cheaply than a
decode, whether (and why not) :func:`decode_image` would accept some bytes.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from hmpf.errors import ImageError

__all__ = ["IMAGE_EXTENSIONS", "decode_image", "load_image", "probe_image", "to_rgb"]

#: File suffixes treated as images when a folder is listed.
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff")

_JPEG_SOI = b"\xff\xd8"
_JPEG_EOI = b"\xff\xd9"
_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND"
#: imdecode flags per size divisor (1: full size).
_REDUCED = {
    1: cv2.IMREAD_COLOR,
    2: cv2.IMREAD_REDUCED_COLOR_2,
    4: cv2.IMREAD_REDUCED_COLOR_4,
    8: cv2.IMREAD_REDUCED_COLOR_8,
}


def _check_complete(data: bytes, source: str) -> None:
    """Reject JPEG/PNG streams whose end marker is missing.

    libjpeg decodes a truncated JPEG into a partly grey image with only a warning on stderr;
    a missing end-of-image marker is the reliable sign of a truncated upload or file.
    """
    if data.startswith(_JPEG_SOI):
        # Some writers append padding after EOI; accept the marker anywhere in the tail.
        if _JPEG_EOI not in data[-4096:]:
            raise ImageError(source, "truncated JPEG (no end-of-image marker)")
    elif data.startswith(_PNG_SIG):
        if _PNG_IEND not in data[-64:]:
            raise ImageError(source, "truncated PNG (no IEND chunk)")


def _check_data(data: bytes, source: str) -> None:
    """The checks on the encoded bytes that come before any decoding: not empty, complete."""
    if len(data) == 0:
        raise ImageError(source, "file is empty")
    _check_complete(data, source)


def to_rgb(image: np.ndarray, source: str = "<array>") -> np.ndarray:
    """Return ``image`` as an H x W x 3 ``uint8`` RGB array (grey becomes 3 equal channels)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ImageError(source, f"expected uint8 pixels, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 2 or img.shape[1] < 2:
        raise ImageError(source, f"unsupported image shape {image.shape}")
    return np.ascontiguousarray(img)


def decode_image(
    data: bytes | bytearray | memoryview, source: str = "<bytes>", reduce: int = 1
) -> np.ndarray:
    """Decode encoded image bytes (JPEG, PNG, WebP, BMP, TIFF) to H x W x 3 RGB ``uint8``.

    Grey and 16-bit images are converted to 8-bit 3-channel; EXIF orientation is applied.
    ``reduce`` (2, 4 or 8) decodes at that fraction of the size (each side rounded up for a
    JPEG, down otherwise): a JPEG through libjpeg's scaled decoding (the full image is never
    held, except a progressive one's coefficients), another format decoded whole, then shrunk
    as 2 x 2 means (OpenCV's reduced decoding) and by area for the rest.

    Raises:
        ImageError: empty, truncated or undecodable data (the message names ``source``).
    """
    buf = bytes(data)
    _check_data(buf, source)
    arr = np.frombuffer(buf, dtype=np.uint8)
    if reduce not in _REDUCED:
        raise ValueError(f"reduce must be one of {sorted(_REDUCED)}, got {reduce}")
    jpeg = buf.startswith(_JPEG_SOI)
    try:
        bgr = cv2.imdecode(arr, _REDUCED[reduce] if jpeg else _REDUCED[min(reduce, 2)])
        if bgr is not None and not jpeg and reduce > 2:
            rows, cols = (bgr.shape[0] * 2) // reduce, (bgr.shape[1] * 2) // reduce
            bgr = cv2.resize(bgr, (max(cols, 1), max(rows, 1)), interpolation=cv2.INTER_AREA)
    except cv2.error as exc:  # e.g. pixel limits inside OpenCV
        raise ImageError(
            source, f"decoder failed ({exc.err.strip() if exc.err else exc})"
        ) from None
    if bgr is None:
        raise ImageError(source, "not a decodable image (JPEG, PNG, WebP, BMP or TIFF)")
    return to_rgb(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), source)


def load_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read and decode the image file at ``path`` to H x W x 3 RGB ``uint8``.

    Raises:
        ImageError: the file is missing, unreadable, empty or not a valid image.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ImageError(str(p), "no such file") from None
    except IsADirectoryError:
        raise ImageError(str(p), "is a directory") from None
    except OSError as exc:
        raise ImageError(str(p), exc.strerror or str(exc)) from None
    return decode_image(data, str(p))


def probe_image(data: bytes | bytearray | memoryview, source: str = "<bytes>") -> str | None:
    """Why :func:`decode_image` would reject ``data``, or None when it would accept it.

    Cheaper than a decode for good images: after :func:`decode_image`'s checks on the bytes
    (empty, missing end marker), the data is decoded at 1/8 scale, which parses all of a
    JPEG's compressed data but skips most of the decoding work (about 0.5 ms instead of
    2.2 ms for a 960 x 540 JPEG). Data that fails this cheap decode is decoded in full by
    :func:`decode_image` itself, so a reason returned is always the one its
    :class:`~hmpf.errors.ImageError` gives (``source`` only matters to that decode's error).
    A None verdict cannot foresee failures that only a full-size decode meets (e.g. memory).

    Returns:
        None (decodable), or the ``reason`` text of the error :func:`decode_image` raises.
    """
    buf = bytes(data)
    try:
        _check_data(buf, source)
    except ImageError as exc:
        return exc.reason
    try:
        small = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    except cv2.error:
        small = None
    # 2 x 2 pixels at 1/8 scale: at least 9 x 9 at full size, so to_rgb's size check passes.
    if small is not None and min(small.shape[:2]) >= 2:
        return None
    try:
        decode_image(buf, source)
    except ImageError as exc:
        return exc.reason
    return None
