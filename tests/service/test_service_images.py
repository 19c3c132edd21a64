"""Uploaded images (service/images.py): EXIF orientation in every accepted format, decoding
large images at a reduced size and the decode memory budget.

The test images are built here: OpenCV encodes the pixels and the EXIF orientation tag is
written by hand (a one-entry TIFF IFD in a JPEG APP1 segment, a PNG ``eXIf`` chunk or a WebP
``EXIF`` chunk of an extended ``VP8X`` file).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from service.images import decode_cost, decode_upload
from service.metrics import Metrics
from service.routes.localize import Localizer, Upload
from service.schemas import LocalizeParams
from service.settings import load_settings

# -- building images with an orientation tag ---------------------------------------------------


def _tiff(orientation: int) -> bytes:
    """A big-endian TIFF header and one IFD with the Orientation tag (0x0112, SHORT)."""
    entry = struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0)
    return b"MM\x00*" + struct.pack(">I", 8) + struct.pack(">H", 1) + entry + b"\x00" * 4


def _encode(ext: str, bgr: np.ndarray, *params: int) -> bytes:
    ok, buf = cv2.imencode(ext, bgr, list(params))
    assert ok
    return buf.tobytes()


def jpeg_with(bgr: np.ndarray, orientation: int | None) -> bytes:
    data = _encode(".jpg", bgr, cv2.IMWRITE_JPEG_QUALITY, 95)
    if orientation is None:
        return data
    app1 = b"Exif\x00\x00" + _tiff(orientation)
    return data[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + data[2:]


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    crc = zlib.crc32(kind + body)
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)


def png_with(bgr: np.ndarray, orientation: int | None) -> bytes:
    data = _encode(".png", bgr)
    if orientation is None:
        return data
    ihdr_end = 8 + 25  # signature, then IHDR (length, type, 13 bytes, CRC)
    return data[:ihdr_end] + _png_chunk(b"eXIf", _tiff(orientation)) + data[ihdr_end:]


def webp_with(bgr: np.ndarray, orientation: int | None) -> bytes:
    data = _encode(".webp", bgr, cv2.IMWRITE_WEBP_QUALITY, 101)  # > 100: lossless
    if orientation is None:
        return data
    assert data[:4] == b"RIFF" and data[8:12] == b"WEBP"
    h, w = bgr.shape[:2]
    vp8x = (
        b"VP8X"
        + struct.pack("<I", 10)
        + bytes([0x08, 0, 0, 0])  # flags: EXIF present
        + (w - 1).to_bytes(3, "little")
        + (h - 1).to_bytes(3, "little")
    )
    tiff = _tiff(orientation)
    exif = b"EXIF" + struct.pack("<I", len(tiff)) + tiff + b"\x00" * (len(tiff) % 2)
    payload = b"WEBP" + vp8x + data[12:] + exif
    return b"RIFF" + struct.pack("<I", len(payload)) + payload


BUILDERS: dict[str, Callable[[np.ndarray, int | None], bytes]] = {
    "jpeg": jpeg_with,
    "png": png_with,
    "webp": webp_with,
}

#: What EXIF orientation 1-8 asks a viewer to do to the stored pixels (H x W x C arrays).
ORIENT: dict[int, Callable[[np.ndarray], np.ndarray]] = {
    1: lambda a: a,
    2: lambda a: a[:, ::-1],  # mirror left-right
    3: lambda a: a[::-1, ::-1],  # rotate 180
    4: lambda a: a[::-1],  # mirror top-bottom
    5: lambda a: a.transpose(1, 0, 2),  # transpose (main diagonal)
    6: lambda a: np.rot90(a, -1),  # rotate 90 clockwise
    7: lambda a: np.rot90(a, 2).transpose(1, 0, 2),  # transverse (anti-diagonal)
    8: lambda a: np.rot90(a, 1),  # rotate 90 counter-clockwise
}


def _pattern(h: int = 48, w: int = 80) -> np.ndarray:
    """An asymmetric BGR picture of 8 x 8 blocks (every flip or rotation of it differs)."""
    rng = np.random.default_rng(7)
    blocks = rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8)
    return np.ascontiguousarray(np.kron(blocks, np.ones((8, 8, 1), np.uint8)))


# -- orientation ---------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", sorted(BUILDERS))
@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_format_applies_every_exif_orientation(kind: str, orientation: int) -> None:
    bgr = _pattern()
    build = BUILDERS[kind]
    # The same compressed pixels without the tag: the oriented answer is this one, transformed.
    plain = decode_upload(build(bgr, None), max_pixels=10**6)
    if kind != "jpeg":  # lossless
        np.testing.assert_array_equal(plain, bgr[:, :, ::-1])
    out = decode_upload(build(bgr, orientation), max_pixels=10**6)
    np.testing.assert_array_equal(out, ORIENT[orientation](plain))


# -- large images: reduced decoding and the decode budget ---------------------------------------


def _large(h: int, w: int) -> np.ndarray:
    """A smooth BGR picture (gradients and a disc), cheap to encode at any size."""
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 255 // w, y * 255 // h, (x + y) * 127 // (w + h)], axis=2).astype(np.uint8)
    cv2.circle(img, (w // 3, h // 2), min(h, w) // 4, (20, 200, 40), -1)
    return img


@pytest.mark.parametrize("kind", ["jpeg", "png", "webp"])
@pytest.mark.parametrize("orientation", [1, 6])
def test_a_large_image_is_decoded_reduced_to_the_working_size(kind: str, orientation: int) -> None:
    bgr = _large(1700, 2300)  # shorter side 1700: halved (850 >= 800), not quartered
    data = BUILDERS[kind](bgr, orientation)
    out = decode_upload(data, max_pixels=10**7, decode_side=800)
    full = decode_upload(data, max_pixels=10**7)  # no working size: the whole image
    assert full.shape[:2] == ((1700, 2300) if orientation == 1 else (2300, 1700))
    assert out.shape == (full.shape[0] // 2, full.shape[1] // 2, 3)
    # the same picture as the full decode shrunk by 2 (2 x 2 box), up to rounding and JPEG
    area = cv2.resize(full, out.shape[1::-1], interpolation=cv2.INTER_AREA)
    diff = np.abs(out.astype(np.int16) - area.astype(np.int16))
    assert diff.mean() < (1.5 if kind == "jpeg" else 0.6), diff.mean()


def test_reduction_steps_and_images_at_the_working_size_are_untouched() -> None:
    bgr = _large(600, 900)
    data = BUILDERS["jpeg"](bgr, None)
    same = decode_upload(data, max_pixels=10**7, decode_side=300)  # 600 = 2 x 300: halved
    assert same.shape == (300, 450, 3)
    for side, shape in ((301, (600, 900)), (150, (150, 225)), (75, (75, 113)), (10, (75, 113))):
        assert decode_upload(data, max_pixels=10**7, decode_side=side).shape[:2] == shape, side
    np.testing.assert_array_equal(
        decode_upload(data, max_pixels=10**7, decode_side=301),
        decode_upload(data, max_pixels=10**7),
    )


def test_decode_cost_counts_what_the_decoder_holds() -> None:
    baseline = BUILDERS["jpeg"](_large(1600, 2400), None)
    progressive = _encode(".jpg", _large(1600, 2400), cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
    png = BUILDERS["png"](_large(1600, 2400), None)
    full = 1600 * 2400 * 3
    assert decode_cost(baseline, 0) == full
    assert decode_cost(baseline, 400) == full // 16  # libjpeg decodes at 1/4 directly
    assert decode_cost(progressive, 400) == full  # its coefficients are held whole
    assert decode_cost(png, 400) == full  # decoded whole, then shrunk
    assert decode_cost(b"not an image", 400) == 0  # refused on its own later
    assert decode_cost(png, 400, max_pixels=1600 * 2400 - 1) == 0  # as is one over the limit


def test_the_routes_decode_at_the_working_size_of_the_settings(tmp_path: Path) -> None:
    settings = load_settings(None, index=tmp_path, auth=False, decode_side=300)
    engine = SimpleNamespace(admit=lambda n: True, workers=1, compute=None)
    localizer = Localizer(engine, settings, Metrics(), None)  # type: ignore[arg-type]
    data = BUILDERS["jpeg"](_large(600, 900), None)
    (query,) = localizer.queries(LocalizeParams(), [Upload(data, "image/jpeg", "image")])
    assert query.decode_side == 300
    assert decode_upload(data, max_pixels=10**7, decode_side=query.decode_side).shape[:2] == (
        300,
        450,
    )
