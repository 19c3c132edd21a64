"""Uploaded images: type sniffing and the pixel count read from the header, before decoding.

Only JPEG, PNG and WebP are accepted. The format is taken from the bytes (magic numbers), not
from the declared content type; a declared type that is not an image type we accept is a 415.
The width and height are read from the container header (JPEG SOFn, PNG IHDR, WebP VP8 /
VP8L / VP8X) so that a decompression bomb is refused before any pixel is decoded. The EXIF
orientation is applied for every format (so tags 5-8 swap the header's width and height).

Large images are decoded straight to a working size (``decode_side``, the shorter side kept at
or above it; :func:`reduction`): a JPEG at 1/2, 1/4 or 1/8 by libjpeg's scaled decoding,
without ever holding the full image (unless progressive); a PNG or WebP is decoded whole, then
shrunk. The methods resize every image to at most a few hundred pixels a side, so the answer
hardly changes, while a 6000 x 6000 upload costs a fraction of the time and memory. What a
request's images cost the decoder (:func:`decode_cost`) is checked against a budget before
any is decoded (:func:`check_decode_budget`, 413 ``decode_budget_exceeded``).
"""

from __future__ import annotations

import struct

import numpy as np

from hmpf.errors import ImageError
from hmpf.imageio import decode_image
from service.errors import ApiError

__all__ = [
    "ACCEPTED_TYPES",
    "check_decode_budget",
    "decode_cost",
    "decode_upload",
    "image_size",
    "reduction",
    "sniff",
]

ACCEPTED_TYPES = {
    "image/jpeg": "jpeg",
    "image/jpg": "jpeg",
    "image/png": "png",
    "image/webp": "webp",
}
#: Other image formats we recognise only to answer 415 instead of 422.
_OTHER = {b"GIF87a": "gif", b"GIF89a": "gif", b"BM": "bmp", b"II*\x00": "tiff", b"MM\x00*": "tiff"}
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
#: SOF markers of progressive JPEGs: libjpeg holds the whole image's coefficients.
_PROGRESSIVE = {0xC2, 0xC6, 0xCA, 0xCE}
#: Bytes per decoded pixel (8-bit RGB).
_BPP = 3


def sniff(data: bytes) -> str | None:
    """``jpeg``, ``png``, ``webp``, another known image format's name, or None."""
    if data.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    for magic, name in _OTHER.items():
        if data.startswith(magic):
            return name
    return None


def image_size(data: bytes, kind: str) -> tuple[int, int] | None:
    """(width, height) from the header of a ``jpeg`` / ``png`` / ``webp`` stream, or None."""
    try:
        if kind == "png":
            if data[12:16] != b"IHDR":
                return None
            w, h = struct.unpack(">II", data[16:24])
            return int(w), int(h)
        if kind == "webp":
            return _webp_size(data)
        if kind == "jpeg":
            frame = _jpeg_frame(data)
            return None if frame is None else frame[1:]
    except (struct.error, IndexError):
        return None
    return None


def _jpeg_frame(data: bytes) -> tuple[int, int, int] | None:
    """(SOF marker, width, height) of a JPEG stream, or None."""
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in _SOF:
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return marker, int(w), int(h)
        if marker in (0xD9, 0xDA) or length < 2:  # end of image / start of scan before SOF
            return None
        i += 2 + length
    return None


def _webp_size(data: bytes) -> tuple[int, int] | None:
    chunk = data[12:16]
    if chunk == b"VP8 ":
        if data[23:26] != b"\x9d\x01\x2a":
            return None
        w, h = struct.unpack("<HH", data[26:30])
        return int(w & 0x3FFF), int(h & 0x3FFF)
    if chunk == b"VP8L":
        if data[20] != 0x2F:
            return None
        (bits,) = struct.unpack("<I", data[21:25])
        return int((bits & 0x3FFF) + 1), int(((bits >> 14) & 0x3FFF) + 1)
    if chunk == b"VP8X":
        w = int.from_bytes(data[24:27], "little") + 1
        h = int.from_bytes(data[27:30], "little") + 1
        return w, h
    return None


def check_content_type(content_type: str | None) -> None:
    """415 unless the declared type is one we accept (``None``: not declared, allowed)."""
    if content_type is None:
        return
    base = content_type.split(";", 1)[0].strip().lower()
    if base in ("", "application/octet-stream"):
        return
    if base not in ACCEPTED_TYPES:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"content type {base!r} is not accepted; send image/jpeg, image/png or image/webp",
        )


def reduction(width: int, height: int, side: int) -> int:
    """The divisor an image is decoded at: 1, 2, 4 or 8, the largest that keeps its shorter
    side at least ``side`` (0: always 1, the full size)."""
    k = 1
    while side > 0 and k < 8 and min(width, height) >= 2 * k * side:
        k *= 2
    return k


def decode_cost(data: bytes, side: int, max_pixels: int | None = None) -> int:
    """The bytes of pixels the decoder holds for ``data`` decoded at working size ``side``:
    the reduced image for a baseline JPEG, the full image otherwise (a PNG or WebP is decoded
    whole before it is shrunk, a progressive JPEG keeps all its coefficients). 0 for data that
    is never decoded (refused on its own): a header that cannot be read, more pixels than
    ``max_pixels``."""
    kind = sniff(data)
    if kind not in ("jpeg", "png", "webp"):
        return 0
    size = image_size(data, kind)
    if size is None or (max_pixels is not None and size[0] * size[1] > max_pixels):
        return 0
    w, h = size
    k = reduction(w, h, side)
    if kind == "jpeg" and k > 1:
        frame = _jpeg_frame(data)
        if frame is not None and frame[0] not in _PROGRESSIVE:
            return -(-w // k) * -(-h // k) * _BPP
    return w * h * _BPP


def check_decode_budget(uploads: list[bytes], budget: int, side: int, max_pixels: int) -> None:
    """413 ``decode_budget_exceeded`` when a request's images together cost the decoder more
    than ``budget`` bytes (:func:`decode_cost`; counted as if decoded at once)."""
    total = sum(decode_cost(data, side, max_pixels) for data in uploads)
    if total > budget:
        what = "the image decodes" if len(uploads) == 1 else f"the {len(uploads)} images decode"
        raise ApiError(
            413,
            "decode_budget_exceeded",
            f"{what} to {total} bytes of pixels, over the limit of {budget} per request; "
            "send fewer or smaller images",
        )


def decode_upload(
    data: bytes,
    *,
    max_pixels: int,
    content_type: str | None = None,
    source: str = "image",
    decode_side: int = 0,
) -> np.ndarray:
    """Check and decode one uploaded image to RGB ``uint8``, reduced to the working size
    ``decode_side`` (:func:`reduction`; 0: the full size).

    Raises:
        ApiError: 415 (not JPEG/PNG/WebP), 413 (too many pixels), 422 (empty, truncated or
            undecodable).
    """
    check_content_type(content_type)
    if not data:
        raise ApiError(422, "invalid_image", f"{source}: the upload is empty")
    kind = sniff(data)
    if kind is None:
        raise ApiError(
            422, "invalid_image", f"{source}: not a JPEG, PNG or WebP image (unknown content)"
        )
    if kind not in ("jpeg", "png", "webp"):
        raise ApiError(
            415, "unsupported_media_type", f"{source}: {kind.upper()} images are not accepted"
        )
    size = image_size(data, kind)
    if size is None:
        raise ApiError(422, "invalid_image", f"{source}: damaged {kind.upper()} header")
    w, h = size
    if w < 2 or h < 2:
        raise ApiError(422, "invalid_image", f"{source}: image of {w} x {h} pixels is too small")
    if w * h > max_pixels:
        raise ApiError(
            413,
            "too_many_pixels",
            f"{source}: {w} x {h} = {w * h} pixels exceeds the limit of {max_pixels}",
        )
    k = reduction(w, h, decode_side)
    try:
        image = decode_image(data, source, reduce=k)
    except ImageError as exc:
        raise ApiError(422, "invalid_image", f"{source}: {exc.reason}") from None
    # An EXIF orientation of 5-8 swaps the axes: OpenCV applies the tag of a JPEG (APP1), a
    # PNG (eXIf) and a WebP (EXIF chunk) alike. Any other size means the header lied.
    rows, cols = image.shape[:2]
    if not (_reduced(w, k, cols) and _reduced(h, k, rows)) and not (
        _reduced(h, k, cols) and _reduced(w, k, rows)
    ):
        raise ApiError(422, "invalid_image", f"{source}: header and pixel data disagree")
    return image


def _reduced(n: int, k: int, got: int) -> bool:
    """Whether ``got`` pixels is ``n`` divided by ``k`` (rounded either way)."""
    return got in (n // k, -(-n // k))
