"""Gist (method id 11): Oliva-Torralba ``LMgist`` with its defaults, 512-D.

Spec §2.2 (docs/spec/gist.md), ported step by step: crop, ``rgb2gray``, then LMgist:

1. ``imresizecrop`` to 128x128: aspect-preserving MATLAB bilinear resize (antialiased), centre
   crop (so the sides of wide frames are discarded, §8.10);
2. stretch to 0..255;
3. ``prefilt`` (fc = 4): log, symmetric padding, Gaussian high-pass and local contrast
   normalisation computed in the Fourier domain;
4. a bank of 4 scales x 8 orientations Gabor filters (``createGabor`` on a 192x192 grid, the image
   being symmetric-padded by 32), applied via FFT: ``|ifft2(F . G_n)|``, vectorised over the bank;
5. 4x4 block means per filter (block-row index fastest), filters in scale-major order.

Distance: Euclidean, lower is better.

Deviations (documented): a constant image, where LMgist divides 0 by 0, gives an all-zero
prefiltered image instead of NaN. The resize is computed in float64 where MATLAB uses single.
The filter bank is applied as two passes of 1-D inverse FFTs: the first runs only along the
frequency lines where a filter exceeds ``gabor_floor`` (1e-8 of its peak; about 47 % of the
lines), the second only over the central crop (:class:`GaborLines`). The result equals the
full ``ifft2`` to single precision (tested); ``gabor_floor: 0`` computes every line.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import numpy as np
import scipy.fft
from pydantic import Field

from hmpf.imops import imresize, initcrop, rgb2gray
from hmpf.methods.base import (
    GlobalMethod,
    MethodConfig,
    MetricSpec,
    ReferenceFitConfig,
    euclidean,
)
from hmpf.methods.registry import register
from hmpf.runtime import compute_threads


class GistConfig(ReferenceFitConfig):
    image_size: int = Field(128, ge=16)
    orientations_per_scale: tuple[int, ...] = (8, 8, 8, 8)
    number_blocks: int = Field(4, ge=1)
    fc_prefilt: float = Field(4.0, gt=0)
    boundary_extension: int = Field(32, ge=0)
    #: Gabor values below this (relative to the peak of 1) are treated as zero; see GaborLines.
    gabor_floor: float = Field(1e-8, ge=0, le=1e-4)


def imresizecrop(img: np.ndarray, size: int) -> np.ndarray:
    """LMgist ``imresizecrop``: aspect-preserving bilinear resize then centre crop to size^2."""
    h, w = img.shape
    s = max(size / h, size / w)
    nr, nc = int(np.floor(h * s + 0.5)), int(np.floor(w * s + 0.5))
    out = imresize(img.astype(np.float64), (nr, nc), "bilinear")
    sr, sc = (nr - size) // 2, (nc - size) // 2
    return out[sr : sr + size, sc : sc + size]


def prefilt(img: np.ndarray, fc: float = 4.0) -> np.ndarray:
    """LMgist ``prefilt``: whitening and local contrast normalisation (same size as ``img``)."""
    w = 5
    s1 = fc / np.sqrt(np.log(2))
    x = np.log(img + 1.0)
    x = np.pad(x, w, mode="symmetric")
    sn, sm = x.shape
    n = max(sn, sm)
    n += n % 2
    x = np.pad(x, ((0, n - sn), (0, n - sm)), mode="symmetric")
    f = np.arange(-n // 2, n // 2)
    fx, fy = np.meshgrid(f, f)
    gf = np.fft.fftshift(np.exp(-(fx**2 + fy**2) / s1**2))
    # gf is even in frequency, so the filtered images are real: half-spectrum FFTs give the
    # same values as MATLAB's real(ifft2(fft2(.) .* gf)) with half the work.
    half = gf[:, : n // 2 + 1]
    out = x - scipy.fft.irfft2(scipy.fft.rfft2(x) * half, s=x.shape)
    localstd = np.sqrt(np.abs(scipy.fft.irfft2(scipy.fft.rfft2(out**2) * half, s=x.shape)))
    out = out / (0.2 + localstd)
    return out[w : sn - w, w : sm - w]


def create_gabor(orientations: tuple[int, ...], n: int) -> np.ndarray:
    """LMgist ``createGabor``: (n_filters, n, n) transfer functions, scale-major order."""
    params = []
    for i, n_or in enumerate(orientations):  # i = 0 is the highest frequency
        for j in range(n_or):
            params.append((0.35, 0.3 / 1.85**i, 16.0 * n_or**2 / 32.0**2, np.pi / n_or * j))
    p = np.array(params)  # (F, 4)
    f = np.arange(-n // 2, n // 2)
    fx, fy = np.meshgrid(f, f)
    fr = np.fft.fftshift(np.sqrt(fx**2 + fy**2))
    t = np.fft.fftshift(np.angle(fx + 1j * fy))
    tr = t[None] + p[:, 3, None, None]
    tr = tr + 2 * np.pi * (tr < -np.pi) - 2 * np.pi * (tr > np.pi)
    return np.exp(
        -10 * p[:, 0, None, None] * (fr[None] / n / p[:, 1, None, None] - 1) ** 2
        - 2 * p[:, 2, None, None] * np.pi * tr**2
    )


def block_edges(length: int, blocks: int) -> np.ndarray:
    """MATLAB ``fix(linspace(0, length, blocks + 1))``."""
    return np.trunc(np.linspace(0, length, blocks + 1)).astype(np.int64)


@dataclass(frozen=True)
class GaborLines:
    """A Gabor bank stored as the frequency lines where each filter is not negligible.

    ``|ifft2(F . G_n)|`` is computed as two passes of 1-D inverse FFTs. A Gabor transfer
    function is concentrated in one wedge of the spectrum, so for each filter most frequency
    columns (or rows) are zero to within ``floor`` (relative to the filter's peak of 1). The
    first pass runs only along those lines, oriented along whichever axis has fewer of them
    (about 47 % of the full work for the LMgist bank at ``floor = 1e-8``); the second pass
    runs over the central crop only. Values below ``floor`` are ~1e-8 of the filter's peak,
    beneath single precision (the original computes in single), so the result equals the
    full computation to float32 rounding (tested).

    Attributes:
        transposed: (F,) bool, True where a filter's lines are spectrum rows instead of columns.
        line_index: (L,) indices into the stacked ``[spec.T; spec]`` (2n, n) line table.
        slot: (L,) indices into the (F * n) second-pass buffer lines.
        values: (L, n) complex64 filter values along each kept line.
    """

    n: int
    transposed: np.ndarray
    line_index: np.ndarray
    slot: np.ndarray
    values: np.ndarray

    @classmethod
    def from_filters(cls, filters: np.ndarray, floor: float) -> GaborLines:
        n_f, n, _ = filters.shape
        transposed, index, slot, values = [], [], [], []
        for f, g in enumerate(filters):
            mask = np.abs(g) > floor
            cols, rows = np.flatnonzero(mask.any(axis=0)), np.flatnonzero(mask.any(axis=1))
            t = len(rows) < len(cols)
            lines = rows if t else cols
            transposed.append(t)
            # Column lines are rows of spec.T (table offset 0); row lines are rows of spec (n).
            index.append(lines + (n if t else 0))
            slot.append(f * n + lines)
            values.append(g[lines] if t else g[:, lines].T)
        return cls(
            n=n,
            transposed=np.array(transposed),
            line_index=np.concatenate(index),
            slot=np.concatenate(slot),
            values=np.concatenate(values).astype(np.complex64),
        )

    def block_means(
        self, spec: np.ndarray, be: int, size: int, blocks: int, workers: int = 1
    ) -> np.ndarray:
        """(F, blocks, blocks) block means of ``|ifft2(spec . G_f)|`` over the central crop.

        The crop is ``[be:be+size]`` on both axes; blocks follow ``fix(linspace(0, size,
        blocks + 1))``; the result is indexed ``[filter, block_row, block_col]``.
        """
        n, n_f = self.n, len(self.transposed)
        table = np.concatenate([spec.T, spec]).astype(np.complex64, copy=False)
        lines = table[self.line_index] * self.values  # (L, n): spectrum along each kept line
        first = scipy.fft.ifft(lines, axis=1, workers=workers, overwrite_x=True)
        buf = np.zeros((n_f * n, size), dtype=np.complex64)
        buf[self.slot] = first[:, be : be + size]
        second = scipy.fft.ifft(
            buf.reshape(n_f, n, size), axis=1, workers=workers, overwrite_x=True
        )
        mag = np.abs(second[:, be : be + size])  # (F, a, b): a second-pass, b first-pass axis
        if size % blocks == 0:
            w = size // blocks
            means = mag.reshape(n_f, blocks, w, blocks, w).mean(axis=(2, 4), dtype=np.float64)
        else:
            edges = block_edges(size, blocks)
            sums = np.add.reduceat(np.add.reduceat(mag, edges[:-1], axis=1), edges[:-1], axis=2)
            means = sums / (np.diff(edges)[:, None] * np.diff(edges)[None, :])[None]
        # Column-line filters ran along y first, so their blocks come out as (x, y).
        means[~self.transposed] = means[~self.transposed].transpose(0, 2, 1)
        return means


@register
class Gist(GlobalMethod):
    name = "gist"
    higher_is_better = False
    Config: ClassVar[type[MethodConfig]] = GistConfig
    dim = 512

    def __init__(self, config: GistConfig | None = None) -> None:
        super().__init__(config)
        c: GistConfig = self.config  # type: ignore[assignment]
        self.dim = sum(c.orientations_per_scale) * c.number_blocks**2

    @cached_property
    def filters(self) -> np.ndarray:
        c: GistConfig = self.config  # type: ignore[assignment]
        n = c.image_size + 2 * c.boundary_extension
        return create_gabor(c.orientations_per_scale, n)

    @cached_property
    def bank(self) -> GaborLines:
        return GaborLines.from_filters(self.filters, self.config.gabor_floor)  # type: ignore[attr-defined]

    def describe(self, grey: np.ndarray) -> np.ndarray:
        """LMgist on a 2-D grey image (any dtype): the ``dim``-vector, float32."""
        c: GistConfig = self.config  # type: ignore[assignment]
        img = imresizecrop(np.asarray(grey, dtype=np.float64), c.image_size)
        img = img - img.min()
        peak = img.max()
        img = 255.0 * img / peak if peak > 0 else img
        out = prefilt(img, c.fc_prefilt)
        be, size = c.boundary_extension, c.image_size
        spec = scipy.fft.fft2(np.pad(out, be, mode="symmetric").astype(np.float32))
        means = self.bank.block_means(spec, be, size, c.number_blocks, compute_threads())
        # means[f, block_row, block_col]; column-major block order: block-row index fastest.
        return means.transpose(0, 2, 1).reshape(-1).astype(np.float32)

    def raw_descriptor(self, image: np.ndarray) -> np.ndarray:
        return self.describe(initcrop(rgb2gray(image)))

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    def faiss_metric(self) -> MetricSpec:
        return MetricSpec("l2", 1.0)
