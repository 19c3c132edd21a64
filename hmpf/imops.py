"""Image operations with MATLAB semantics (spec §1, docs/spec/images.md).

* :func:`initcrop` — the original's ``initCrop = [1 1 1 1]``: drops the last row and column.
* :func:`imresize` — MATLAB ``imresize(I, [rows cols], method)`` with antialiasing when shrinking,
  mirrored borders, normalised weights, the dimension with the smaller scale first, and
  uint8 rounding after each pass, as MATLAB does.
* :func:`rgb2gray` — MATLAB ``rgb2gray`` (0.2989 R + 0.5870 G + 0.1140 B, rounded for uint8).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np
import scipy.sparse as sp

__all__ = ["imresize", "initcrop", "rgb2gray", "round_half_away"]

_EPS = np.finfo(np.float64).eps
# MATLAB rgb2gray weights x 10000, for exact integer arithmetic on uint8 input.
_GREY_WEIGHTS = np.array([[2989.0, 5870.0, 1140.0]], dtype=np.float32)


def _lanczos3(x: np.ndarray) -> np.ndarray:
    # MATLAB's definition, including its eps guard at x = 0.
    f = (np.sin(np.pi * x) * np.sin(np.pi * x / 3) + _EPS) / ((np.pi**2 * x**2 / 3) + _EPS)
    return f * (np.abs(x) < 3)


def _triangle(x: np.ndarray) -> np.ndarray:
    return (x + 1) * ((x >= -1) & (x < 0)) + (1 - x) * ((x >= 0) & (x <= 1))


def _cubic(x: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    ax2, ax3 = ax**2, ax**3
    return (1.5 * ax3 - 2.5 * ax2 + 1) * (ax <= 1) + (-0.5 * ax3 + 2.5 * ax2 - 4 * ax + 2) * (
        (ax > 1) & (ax <= 2)
    )


_KERNELS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], float]] = {
    "lanczos3": (_lanczos3, 6.0),
    "bilinear": (_triangle, 2.0),
    "bicubic": (_cubic, 4.0),
}


@lru_cache(maxsize=64)
def _weights(in_len: int, out_len: int, method: str) -> sp.csr_matrix:
    """Sparse (out_len x in_len) resampling matrix, MATLAB ``contributions`` semantics."""
    kernel, width = _KERNELS[method]
    scale = out_len / in_len
    h: Callable[[np.ndarray], np.ndarray] = kernel
    if scale < 1:  # antialiasing: widen the kernel by 1/scale

        def widened(x: np.ndarray) -> np.ndarray:
            return scale * kernel(scale * x)

        h = widened
        width = width / scale
    x = np.arange(1, out_len + 1, dtype=np.float64)
    u = x / scale + 0.5 * (1 - 1 / scale)
    left = np.floor(u - width / 2)
    taps = int(np.ceil(width)) + 2
    idx = left[:, None] + np.arange(taps)[None, :]
    w = h(u[:, None] - idx)
    w = w / w.sum(axis=1, keepdims=True)
    # Mirror out-of-range taps: aux = [1..n, n..1] (1-based), as in MATLAB.
    aux = np.concatenate([np.arange(in_len), np.arange(in_len)[::-1]])
    cols = aux[np.mod(idx.astype(np.int64) - 1, 2 * in_len)]
    rows = np.repeat(np.arange(out_len), taps)
    m = sp.coo_matrix((w.ravel(), (rows, cols.ravel())), shape=(out_len, in_len))
    return m.tocsr()  # duplicates (mirrored taps hitting the same pixel) are summed


def round_half_away(x: np.ndarray) -> np.ndarray:
    """MATLAB ``round``: halves go away from zero (numpy's ``round`` goes to even)."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _resize_axis(img: np.ndarray, out_len: int, axis: int, method: str) -> np.ndarray:
    in_len = img.shape[axis]
    moved = np.moveaxis(img, axis, 0)
    rest = moved.shape[1:]
    flat = moved.reshape(in_len, -1).astype(np.float64, copy=False)
    out = _weights(in_len, out_len, method) @ flat
    return np.moveaxis(out.reshape((out_len, *rest)), 0, axis)


def imresize(img: np.ndarray, size: tuple[int, int], method: str = "lanczos3") -> np.ndarray:
    """Resize like MATLAB ``imresize(img, [rows cols], method)``.

    Args:
        img: H x W or H x W x C array, ``uint8`` or floating point.
        size: output ``(rows, cols)``.
        method: ``"lanczos3"``, ``"bilinear"`` or ``"bicubic"``.

    Returns:
        rows x cols (x C) array; ``uint8`` input gives ``uint8`` output (rounded and saturated
        after each pass, as MATLAB does), float input gives float64.
    """
    if method not in _KERNELS:
        raise ValueError(f"unknown resize method {method!r}; use one of {sorted(_KERNELS)}")
    rows, cols = int(size[0]), int(size[1])
    is_u8 = img.dtype == np.uint8
    scale = (rows / img.shape[0], cols / img.shape[1])
    order = (0, 1) if scale[0] <= scale[1] else (1, 0)
    out: np.ndarray = img
    for axis in order:
        target = rows if axis == 0 else cols
        if out.shape[axis] == target:
            continue
        out = _resize_axis(out, target, axis, method)
        if is_u8:
            out = np.clip(np.floor(out + 0.5), 0, 255).astype(np.uint8)
    if is_u8:
        return np.ascontiguousarray(out, dtype=np.uint8)
    return np.ascontiguousarray(out, dtype=np.float64)


def rgb2gray(img: np.ndarray) -> np.ndarray:
    """MATLAB ``rgb2gray``; a 2-D input is returned unchanged. uint8 in -> uint8 out (rounded).

    For uint8 the weighted sum is computed exactly in integers (``2989 R + 5870 G + 1140 B``
    over 10000) and rounded half away from zero, as MATLAB's ``round`` does.
    """
    if img.ndim == 2:
        return img
    if img.dtype == np.uint8:
        # float32 holds the integer sums exactly (< 2^24) and division by 10000 is correctly
        # rounded, so truncating (v + 5000) / 10000 gives the exact integer quotient (<= 255).
        # cv2.transform, not a BLAS matmul: BLAS threads would fight OpenCV's for the cores.
        v: np.ndarray = cv2.transform(img[..., :3].astype(np.float32), _GREY_WEIGHTS)
        v += np.float32(5000)
        v /= np.float32(10000)
        return v.astype(np.uint8)
    return img[..., :3].astype(np.float64) @ np.array([0.2989, 0.5870, 0.1140])


def initcrop(img: np.ndarray) -> np.ndarray:
    """The original ``initCrop = [1 1 1 1]``: rows ``1:H-1`` and columns ``1:W-1`` (1-based).

    Only the last row and the last column are removed (spec §1.3, §8.21).
    """
    return img[:-1, :-1]
