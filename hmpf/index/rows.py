"""Rows of a stored matrix read on demand, and a bounded cache of local features.

A map of a million references cannot hold every method's matrix in memory (a NetVLAD
descriptor alone is 24 KiB as float32). What every query touches stays resident (tier 1's
FAISS codes and a fixed sample of rows); what a query reads for a handful of candidates is
read from the version's files when it is needed:

* :class:`DiskRows`: an ``(N, D)`` matrix stored contiguously in an HDF5 file, read row by row
  with ``os.pread`` (no memory map, so the process's resident memory does not grow with the
  rows it has read: the operating system's page cache holds them, shared with every other
  process reading the same file and given back under memory pressure). Rows come back in the
  dtype the method produced (float16 storage is widened exactly), so scores are those of the
  in-memory matrix bit for bit.
* :class:`LruCache`: a thread-safe least-recently-used cache bounded in bytes, for decoded
  local features (KAZE keypoints, OLO regions) of recent candidates.

Both count what they read (:class:`ReadStats`), so a bench can say what a query reads from
disk.
"""

from __future__ import annotations

import os
import sys
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.index.layout import IndexCorruptError

__all__ = ["DiskRows", "LruCache", "ReadStats", "disk_rows", "widen"]

#: Elements from which :func:`widen` converts float16 -> float32 its own way.
_WIDEN_FAST = 1 << 14
#: float16 elements :func:`widen` converts at a time through OpenCV.
_WIDEN_BLOCK = 1 << 24


def widen(a: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``a.astype(dtype, copy=False)``, the same numbers, with a faster large float16 ->
    float32 conversion: numpy converts half floats to single ones slowly (3.0 ms for 256
    NetVLAD rows of 6144 dimensions on an AMD EPYC core, one element at a time). torch's
    vectorised conversion is used when torch is already loaded (a torch CNN's process; it is
    not imported for this: 0.2 ms), else OpenCV's (``cv2.convertFp16``, the CPU's F16C
    instructions; a service extracting with ONNX Runtime). Every float16 is a float32, so
    each way is exact (tested on every bit pattern)."""
    dtype = np.dtype(dtype)
    if a.dtype != np.float16 or dtype != np.float32 or a.size < _WIDEN_FAST:
        return a.astype(dtype, copy=False)
    torch = sys.modules.get("torch")
    if torch is not None:
        return torch.from_numpy(np.ascontiguousarray(a)).to(torch.float32).numpy()
    import cv2  # loaded on the first large half-float read only: index readers need no OpenCV

    flat = np.ascontiguousarray(a).reshape(-1).view(np.int16)
    if flat.size <= _WIDEN_BLOCK:  # one call, its own array: no second copy (a query's rows)
        return cv2.convertFp16(flat[None, :]).reshape(a.shape)
    out = np.empty(flat.shape, dtype=np.float32)
    for lo in range(0, flat.size, _WIDEN_BLOCK):  # an OpenCV matrix counts in int32
        out[lo : lo + _WIDEN_BLOCK] = cv2.convertFp16(flat[None, lo : lo + _WIDEN_BLOCK])[0]
    return out.reshape(a.shape)


@dataclass
class ReadStats:
    """What was read from disk: calls, rows and bytes (cumulative; reset by the caller)."""

    calls: int = 0
    rows: int = 0
    bytes: int = 0

    def add(self, rows: int, nbytes: int) -> None:
        self.calls += 1
        self.rows += rows
        self.bytes += nbytes


class DiskRows:
    """An ``(N, D)`` matrix stored contiguously at ``offset`` in ``path``, read on demand.

    Indexing with an int, a slice or an array of row indices reads just those rows (runs of
    consecutive rows in one ``pread``) and returns them as a new array of ``dtype``;
    ``np.asarray(rows)`` reads everything (what add / remove and old versions' profile
    builds need). Safe to use from several threads (``pread`` has no shared file position).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        offset: int,
        shape: tuple[int, ...],
        stored: np.dtype,
        dtype: np.dtype,
        stats: ReadStats | None = None,
    ) -> None:
        self.path = Path(path)
        self.offset = int(offset)
        self.shape = tuple(int(s) for s in shape)
        self.stored = np.dtype(stored)
        self.dtype = np.dtype(dtype)
        self.row_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * self.stored.itemsize
        self.stats = stats if stats is not None else ReadStats()
        self._fd: int | None = os.open(self.path, os.O_RDONLY)

    def head(self, n: int) -> DiskRows:
        """The first ``n`` rows, read on demand as well (a file handle of its own)."""
        n = min(max(int(n), 0), self.shape[0])
        return DiskRows(
            self.path, self.offset, (n, *self.shape[1:]), self.stored, self.dtype, self.stats
        )

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self) -> None:  # pragma: no cover - interpreter shutdown order varies
        try:
            self.close()
        except Exception:
            pass

    def _read(self, start: int, count: int) -> np.ndarray:
        """Rows ``start .. start + count - 1`` in the stored dtype."""
        buf = np.empty((count, *self.shape[1:]), dtype=self.stored)
        if buf.size:
            self._read_into(memoryview(buf).cast("B"), start, count)  # type: ignore[arg-type]
        return buf

    def _read_into(self, view: memoryview, start: int, count: int) -> None:
        """Rows ``start .. start + count - 1``, stored bytes, into ``view`` (their size)."""
        if self._fd is None:
            raise ValueError(f"{self.path}: read after close")
        want, pos, done = count * self.row_bytes, self.offset + start * self.row_bytes, 0
        while done < want:
            try:
                got = os.preadv(self._fd, [view[done:]], pos + done)
            except OSError as exc:
                raise IndexCorruptError(
                    f"{self.path}: cannot read byte {pos + done} ({exc.strerror})"
                ) from None
            if got <= 0:
                raise IndexCorruptError(
                    f"{self.path}: short read at byte {pos + done} (file truncated?)"
                )
            done += got
        self.stats.add(count, want)

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """Rows ``idx`` (any order, repeats allowed) as ``dtype``."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        n = self.shape[0]
        if idx.size and (idx.min() < -n or idx.max() >= n):
            raise IndexError(f"row index out of range 0 .. {n - 1}")
        idx = np.where(idx < 0, idx + n, idx)
        uniq, inverse = np.unique(idx, return_inverse=True)
        # Every run of consecutive rows is one read, straight into one buffer of the stored
        # dtype, widened once at the end.
        buf = np.empty((len(uniq), *self.shape[1:]), dtype=self.stored)
        if not buf.size:
            return widen(buf, self.dtype)[inverse]
        view = memoryview(buf).cast("B")  # type: ignore[arg-type]
        starts = np.flatnonzero(np.diff(uniq, prepend=-2) != 1)
        counts = np.diff(starts, append=len(uniq))
        rb = self.row_bytes
        runs = zip(starts.tolist(), uniq[starts].tolist(), counts.tolist(), strict=True)
        for at, first, count in runs:
            self._read_into(view[at * rb : (at + count) * rb], first, count)
        out = widen(buf, self.dtype)
        return out[inverse] if len(uniq) != len(idx) or (np.diff(idx) < 0).any() else out

    def __getitem__(self, key: Any) -> np.ndarray:
        if isinstance(key, (int, np.integer)):
            return self.rows(np.array([key]))[0]
        if isinstance(key, slice):
            start, stop, step = key.indices(self.shape[0])
            if step == 1:
                return widen(self._read(start, max(0, stop - start)), self.dtype)
            return self.rows(np.arange(start, stop, step))
        if isinstance(key, tuple):
            return self[key[0]][(slice(None), *key[1:])]
        return self.rows(np.asarray(key))

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = self[:]
        return out if dtype is None else widen(out, dtype)


def disk_rows(dataset: Any, stats: ReadStats | None = None) -> DiskRows | None:
    """A :class:`DiskRows` over an h5py dataset stored contiguously (None when it is chunked
    or empty: the caller reads it into memory instead). The producing dtype is the
    dataset's ``dtype`` attribute, as the index writes it."""
    offset = dataset.id.get_offset()
    if offset is None or dataset.chunks is not None or not dataset.size or dataset.ndim != 2:
        return None
    produced = np.dtype(dataset.attrs.get("dtype", dataset.dtype.str))
    return DiskRows(dataset.file.filename, offset, dataset.shape, dataset.dtype, produced, stats)


class LruCache:
    """A thread-safe least-recently-used cache bounded in bytes (``max_bytes`` 0: off).

    ``get(key, load, size)`` returns the cached value or ``load()``'s, caching it when it
    fits; ``size(value)`` says what a value costs.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def lookup(self, key: Hashable) -> tuple[bool, Any]:
        """``(True, value)`` when cached (and now most recent), else ``(False, None)``."""
        with self._lock:
            hit = self._items.get(key)
            if hit is None:
                self.misses += 1
                return False, None
            self._items.move_to_end(key)
            self.hits += 1
            return True, hit[0]

    def put(self, key: Hashable, value: Any, nbytes: int) -> None:
        """Cache ``value`` (costing ``nbytes``), dropping the least recent entries to fit."""
        if nbytes > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            self._items[key] = (value, nbytes)
            self._bytes += nbytes
            while self._bytes > self.max_bytes:
                _, (_, dropped) = self._items.popitem(last=False)
                self._bytes -= dropped

    def get(self, key: Hashable, load: Callable[[], Any], size: Callable[[Any], int]) -> Any:
        found, value = self.lookup(key)
        if found:
            return value
        value = load()
        self.put(key, value, size(value))
        return value
