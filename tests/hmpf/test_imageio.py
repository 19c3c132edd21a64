from pathlib import Path

import cv2
import numpy as np
import pytest

from hmpf.errors import HmpfError, ImageError
from hmpf.imageio import decode_image, load_image, probe_image, to_rgb


def _encode(ext: str, img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def test_png_roundtrip_is_rgb():
    rgb = np.zeros((10, 12, 3), np.uint8)
    rgb[..., 0] = 200  # red channel
    out = decode_image(_encode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)))
    assert out.shape == (10, 12, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, rgb)


def test_grey_png_becomes_three_channels(tmp_path: Path):
    grey = (np.arange(64 * 32) % 251).astype(np.uint8).reshape(32, 64)
    p = tmp_path / "g.png"
    p.write_bytes(_encode(".png", grey))
    out = load_image(p)
    assert out.shape == (32, 64, 3)
    for c in range(3):
        np.testing.assert_array_equal(out[..., c], grey)


def test_sixteen_bit_png_becomes_uint8():
    img = (np.arange(20 * 30, dtype=np.uint16) * 100).reshape(20, 30)
    out = decode_image(_encode(".png", img))
    assert out.dtype == np.uint8 and out.shape == (20, 30, 3)


def test_to_rgb_handles_grey_and_alpha():
    assert to_rgb(np.zeros((4, 5), np.uint8)).shape == (4, 5, 3)
    assert to_rgb(np.zeros((4, 5, 4), np.uint8)).shape == (4, 5, 3)
    with pytest.raises(ImageError):
        to_rgb(np.zeros((4, 5), np.float32))
    with pytest.raises(ImageError):
        to_rgb(np.zeros((1, 1, 3), np.uint8))


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"", "empty"),
        (b"hello, I am a text file\n" * 20, "not a decodable image"),
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 50, "truncated PNG"),
    ],
)
def test_bad_files_raise_domain_error_naming_the_file(tmp_path: Path, content: bytes, reason: str):
    p = tmp_path / "bad.jpg"
    p.write_bytes(content)
    with pytest.raises(ImageError) as exc:
        load_image(p)
    assert str(p) in str(exc.value)
    assert reason in str(exc.value)
    assert isinstance(exc.value, HmpfError)


def test_truncated_jpeg_is_rejected(tmp_path: Path):
    img = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    data = _encode(".jpg", img)
    assert decode_image(data).shape == (64, 64, 3)
    with pytest.raises(ImageError, match="truncated JPEG"):
        decode_image(data[: len(data) // 2], "upload.jpg")


def test_corrupt_jpeg_body_is_rejected():
    # A JPEG header followed by garbage and an EOI marker: libjpeg cannot decode it.
    data = b"\xff\xd8\xff\xe0" + bytes(range(256)) * 4 + b"\xff\xd9"
    with pytest.raises(ImageError, match="<bytes>"):
        decode_image(data)


def test_missing_file_and_directory(tmp_path: Path):
    with pytest.raises(ImageError, match="no such file"):
        load_image(tmp_path / "nope.png")
    with pytest.raises(ImageError, match="is a directory"):
        load_image(tmp_path)


def test_image_error_pickles():
    import pickle

    err = pickle.loads(pickle.dumps(ImageError("a.png", "broken")))
    assert err.source == "a.png" and "broken" in str(err)


def _probe_cases() -> dict[str, bytes]:
    img = np.random.default_rng(1).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    jpg, png = _encode(".jpg", img), _encode(".png", img)
    return {
        "good.jpg": jpg,
        "good.png": png,
        "small_ok.png": _encode(".png", np.full((2, 3, 3), 200, np.uint8)),  # fails at 1/8
        "one_pixel.png": _encode(".png", np.zeros((1, 1, 3), np.uint8)),
        "truncated.jpg": jpg[: len(jpg) // 2],
        "truncated.png": png[: len(png) // 2],
        "garbage.jpg": b"hello, I am a text file\n" * 20,
        "garbage_after_soi.jpg": b"\xff\xd8\xff\xe0" + bytes(range(256)) * 4 + b"\xff\xd9",
        "empty.png": b"",
    }


@pytest.mark.parametrize("name", sorted(_probe_cases()))
def test_probe_agrees_with_load_image(tmp_path: Path, name: str):
    data = _probe_cases()[name]
    p = tmp_path / name
    p.write_bytes(data)
    try:
        load_image(p)
        expected = None
    except ImageError as exc:
        expected = exc.reason
    assert probe_image(data, str(p)) == expected
    assert probe_image(bytearray(data)) == expected
    assert (expected is None) == (name.startswith(("good", "small_ok")))
