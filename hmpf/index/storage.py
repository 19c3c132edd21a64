"""HDF5 layout of a version and the storage precision policy.

``references.h5``::

    /names            (N,) utf-8 str       file names, the reference order
    /sha256           (N,) S64             sha256 of each image file's bytes
    /sources          (F,) utf-8 str       folders the images were read from
    /source_id        (N,) int32           each image's folder (for ``add --refit``)
    /meta/<column>    (N,) float64 | str   lat, lon, heading, timestamp, sequence (those given);
                                           place, exp_* on a version with experiences
    /global/<id>      (N, D)               one dataset per global method, contiguous (memory-
                                            mappable when stored in its own dtype)

``local.h5``::

    /local/<id>/<array>/data      (sum n_i, ...)   rows of every image   } ragged layout
    /local/<id>/<array>/offsets   (N + 1,) int64                         }
    /local/<id>/<array>/blocks    (N, n, ...)      equal-count layout (OLO's N x R x D)

``state.h5``: ``/<id>/<name>`` fitted parameters (:meth:`Method.state_arrays`).

Every dataset carries attrs ``dtype`` (the dtype the method produced, restored on read).

Precision policy (``precision`` of the build): ``exact`` stores float arrays as float16 only
where every value survives the round trip exactly, so scores over the index equal in-memory
scores bit for bit; ``compact`` stores every float array as float16 (finite and within
float16's range), except for methods that declare ``index_float16 = False``. Integer arrays
(SAD's uint8) are always stored as they are.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hmpf.index.ann import faiss_module
from hmpf.index.layout import IndexCorruptError
from hmpf.index.tables import STORED_COLUMNS, TEXT_COLUMNS, Ragged, RefTable
from hmpf.methods import Method

__all__ = [
    "Precision",
    "read_local_offsets",
    "read_ref_table",
    "read_state",
    "storage_dtype",
    "write_local",
    "write_references",
    "write_state",
]

Precision = Literal["exact", "compact"]
_F16_MAX = float(np.finfo(np.float16).max)


def _h5py() -> Any:
    faiss_module()  # same extra: a clear install hint when missing
    import h5py  # the index extra; ~0.2 s to import

    return h5py


def storage_dtype(method: Method, array: np.ndarray, precision: Precision) -> np.dtype:
    """The dtype ``array`` is stored in (see the module docstring)."""
    a = np.asarray(array)
    if a.dtype.kind != "f" or a.dtype == np.float16 or a.size == 0:
        return a.dtype
    if not np.isfinite(a).all() or float(np.abs(a).max()) > _F16_MAX:
        return a.dtype
    if precision == "compact" and getattr(type(method), "index_float16", True) is not False:
        return np.dtype(np.float16)
    half = a.astype(np.float16)
    return np.dtype(np.float16) if np.array_equal(half.astype(a.dtype), a) else a.dtype


def _put(group: Any, name: str, array: np.ndarray, dtype: np.dtype) -> int:
    ds = group.create_dataset(name, data=np.asarray(array).astype(dtype, copy=False))
    ds.attrs["dtype"] = np.asarray(array).dtype.str
    return int(ds.id.get_storage_size())


def _get(ds: Any, sel: Any = None) -> np.ndarray:
    """Read ``ds[sel]`` (everything when None) and restore the producing dtype."""
    out = ds[()] if sel is None else ds[sel]
    return np.asarray(out).astype(np.dtype(ds.attrs["dtype"]), copy=False)


def write_references(
    path: Path,
    refs: RefTable,
    globals_: Mapping[str, np.ndarray],
    methods: Mapping[str, Method],
    precision: Precision,
) -> dict[str, int]:
    """Write ``references.h5``; returns bytes stored per global method id."""
    h5py = _h5py()
    sizes: dict[str, int] = {}
    with h5py.File(path, "w", libver="latest") as f:
        f.create_dataset(
            "names", data=np.array(refs.names, dtype=object), dtype=h5py.string_dtype()
        )
        f.create_dataset("sha256", data=np.array(refs.sha256, dtype="S64"))
        folders = sorted(set(refs.sources))
        f.create_dataset("sources", data=np.array(folders, dtype=object), dtype=h5py.string_dtype())
        lookup = {s: i for i, s in enumerate(folders)}
        f.create_dataset("source_id", data=np.array([lookup[s] for s in refs.sources], np.int32))
        meta = f.create_group("meta")
        for col in STORED_COLUMNS:
            if col not in refs.meta:
                continue
            if col in TEXT_COLUMNS:
                meta.create_dataset(
                    col, data=np.asarray(refs.meta[col], dtype=object), dtype=h5py.string_dtype()
                )
            else:
                meta.create_dataset(col, data=np.asarray(refs.meta[col], dtype=np.float64))
        g = f.create_group("global")
        for mid, matrix in globals_.items():
            sizes[mid] = _put(g, mid, matrix, storage_dtype(methods[mid], matrix, precision))
    return sizes


def write_local(
    path: Path,
    locals_: Mapping[str, dict[str, Ragged]],
    methods: Mapping[str, Method],
    precision: Precision,
) -> dict[str, int]:
    """Write ``local.h5``; returns bytes stored per local method id."""
    h5py = _h5py()
    sizes: dict[str, int] = {}
    with h5py.File(path, "w", libver="latest") as f:
        root = f.create_group("local")
        for mid, arrays in locals_.items():
            g = root.create_group(mid)
            total = 0
            for key, rag in arrays.items():
                sub = g.create_group(key)
                sub.attrs["scalar"] = rag.scalar
                dtype = storage_dtype(methods[mid], rag.data, precision)
                counts = rag.counts
                if len(counts) > 0 and (counts == counts[0]).all() and not rag.scalar:
                    blocks = rag.data.reshape(len(counts), int(counts[0]), *rag.data.shape[1:])
                    total += _put(sub, "blocks", blocks, dtype)
                else:
                    total += _put(sub, "data", rag.data, dtype)
                    total += _put(sub, "offsets", rag.offsets, np.dtype(np.int64))
            sizes[mid] = total
    return sizes


def write_state(path: Path, methods: Mapping[str, Method]) -> list[str]:
    """Write fitted parameters of every method that has any; returns their ids."""
    h5py = _h5py()
    written = []
    with h5py.File(path, "w", libver="latest") as f:
        for mid, m in methods.items():
            arrays = m.state_arrays()
            if not arrays:
                continue
            g = f.create_group(mid)
            g.attrs["sha256"] = m.state_digest()
            for k in sorted(arrays):  # as state_digest: the bytes do not depend on dict order
                g.create_dataset(k, data=np.asarray(arrays[k]))
            written.append(mid)
    return written


def read_state(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """method id -> fitted arrays."""
    with open_h5(path) as f:
        return {mid: {k: np.asarray(g[k][()]) for k in g} for mid, g in f.items()}


def open_h5(path: Path) -> Any:
    """Open an HDF5 file read-only; damage -> :class:`IndexCorruptError` naming the file."""
    h5py = _h5py()
    try:
        return h5py.File(path, "r")
    except FileNotFoundError:
        raise IndexCorruptError(f"{path}: missing; run `hmpf-index verify`") from None
    except OSError as exc:
        raise IndexCorruptError(
            f"{path}: unreadable HDF5 ({exc}); run `hmpf-index verify` and rebuild, or "
            "switch to a sound version with `hmpf-index use VERSION`"
        ) from None


def read_ref_table(f: Any) -> RefTable:
    """The :class:`RefTable` of an open ``references.h5``."""
    names = [s.decode() if isinstance(s, bytes) else str(s) for s in f["names"][()]]
    sha = [s.decode() for s in f["sha256"][()]]
    meta: dict[str, np.ndarray] = {}
    for col in f["meta"]:
        data = f["meta"][col][()]
        if col in TEXT_COLUMNS:
            meta[col] = np.array(
                [s.decode() if isinstance(s, bytes) else str(s) for s in data], dtype=object
            )
        else:
            meta[col] = np.asarray(data, dtype=np.float64)
    folders = [s.decode() if isinstance(s, bytes) else str(s) for s in f["sources"][()]]
    sources = [folders[i] for i in f["source_id"][()]]
    return RefTable(names, sha, meta, sources)


def read_global(f: Any, mid: str, mmap: bool = True) -> np.ndarray:
    """The (N, D) matrix of a global method, memory-mapped when stored in its own dtype."""
    ds = f["global"][mid]
    dtype = np.dtype(ds.attrs["dtype"])
    offset = ds.id.get_offset()
    if mmap and ds.dtype == dtype and offset is not None and ds.chunks is None and ds.size:
        return np.memmap(f.filename, dtype=dtype, mode="r", offset=offset, shape=ds.shape)
    return _get(ds)


def read_local_offsets(f: Any, mid: str) -> dict[str, np.ndarray | None]:
    """array name -> offsets (None for the equal-count layout)."""
    g = f["local"][mid]
    return {k: (np.asarray(g[k]["offsets"][()]) if "offsets" in g[k] else None) for k in g}


def read_local_items(
    f: Any, mid: str, key: str, idx: np.ndarray, offsets: np.ndarray | None
) -> list[np.ndarray]:
    """Per-image arrays of ``key`` for the images ``idx`` (read without loading the rest)."""
    sub = f["local"][mid][key]
    scalar = bool(sub.attrs["scalar"])
    if offsets is None:
        ds = sub["blocks"]
        order = np.argsort(idx, kind="stable")
        uniq, inv = np.unique(np.asarray(idx)[order], return_inverse=True)
        rows = _get(ds, uniq) if len(uniq) else np.zeros((0, *ds.shape[1:]), ds.dtype)
        out: list[np.ndarray] = [None] * len(idx)  # type: ignore[list-item]
        for j, pos in enumerate(order):
            out[pos] = rows[inv[j]]
        return out
    ds = sub["data"]
    items = [_get(ds, slice(int(offsets[i]), int(offsets[i + 1]))) for i in idx]
    return [a.reshape(()) for a in items] if scalar else items


def read_local_columns(f: Any, mid: str) -> dict[str, Ragged]:
    """Every image's arrays of a local method as :class:`Ragged` (used by add / remove)."""
    g = f["local"][mid]
    out = {}
    for key in g:
        sub = g[key]
        scalar = bool(sub.attrs["scalar"])
        if "blocks" in sub:
            blocks = _get(sub["blocks"])
            n, c = blocks.shape[:2]
            offsets = np.arange(n + 1, dtype=np.int64) * c
            out[key] = Ragged(blocks.reshape(n * c, *blocks.shape[2:]), offsets, scalar)
        else:
            out[key] = Ragged(_get(sub["data"]), np.asarray(sub["offsets"][()]), scalar)
    return out
