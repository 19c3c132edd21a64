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

``profile.h5``: the places' :class:`~hmpf.confidence.ReferenceProfile`, ``/mean`` and ``/std``
(M, P) float64 (one row per profiled method), attrs ``methods`` (JSON list of ids), ``sign``
(M,) and the parameters it was built with (:func:`write_profile`).

Every dataset carries attrs ``dtype`` (the dtype the method produced, restored on read).

Precision policy (``precision`` of the build): ``exact`` stores float arrays as float16 only
where every value survives the round trip exactly, so scores over the index equal in-memory
scores bit for bit; ``compact`` stores every float array as float16 (finite and within
float16's range), except for methods that declare ``index_float16 = False``. Integer arrays
(SAD's uint8) are always stored as they are.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hmpf.confidence import ReferenceProfile, profile_params
from hmpf.errors import HmpfError
from hmpf.index import layout
from hmpf.index.ann import faiss_module
from hmpf.index.layout import IndexCorruptError
from hmpf.index.tables import STORED_COLUMNS, TEXT_COLUMNS, Ragged, RefTable
from hmpf.methods import Method

__all__ = [
    "Precision",
    "RowBlocks",
    "read_local_offsets",
    "read_profile",
    "read_ref_table",
    "read_state",
    "storage_dtype",
    "stored_profile",
    "write_local",
    "write_profile",
    "write_references",
    "write_state",
]

Precision = Literal["exact", "compact"]
log = logging.getLogger("hmpf.index")
_F16_MAX = float(np.finfo(np.float16).max)


class RowBlocks:
    """An ``(N, ...)`` array given block by block, for an array too large to hold in memory.

    The writers take it wherever they take an array (:func:`write_references`' global
    matrices; :func:`write_local`'s arrays, as the equal-count ``blocks`` layout ``(N, n,
    ...)``) and store the same contiguous dataset the whole array would give, by the same
    precision policy (:func:`storage_dtype`), holding one block at a time;
    :mod:`indexer.build` trains and fills a FAISS index from it the same way.

    Args:
        shape: ``(N, ...)``.
        dtype: the dtype of the rows (the method's, as an array of them would have).
        rows: ``rows(start, stop)`` -> rows ``start .. stop - 1`` as an array; the same
            values on every call (a writer may read them more than once).
        block_rows: rows asked for at once.
    """

    def __init__(
        self,
        shape: Sequence[int],
        dtype: Any,
        rows: Callable[[int, int], np.ndarray],
        block_rows: int = 8192,
    ) -> None:
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self._rows = rows
        self.block_rows = max(1, int(block_rows))

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def __len__(self) -> int:
        return self.shape[0]

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start .. stop - 1``, checked against :attr:`shape` and :attr:`dtype`."""
        out = np.asarray(self._rows(start, stop), dtype=self.dtype)
        if out.shape != (stop - start, *self.shape[1:]):
            raise ValueError(
                f"rows({start}, {stop}) gave shape {out.shape}, expected "
                f"{(stop - start, *self.shape[1:])}"
            )
        return out

    def blocks(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(start, rows)`` of every block, in order."""
        for start in range(0, self.shape[0], self.block_rows):
            yield start, self.rows(start, min(self.shape[0], start + self.block_rows))

    def take(self, idx: np.ndarray) -> np.ndarray:
        """Rows ``idx`` (sorted, unique), reading only the blocks that hold some of them."""
        idx = np.asarray(idx, dtype=np.int64)
        out = np.empty((len(idx), *self.shape[1:]), dtype=self.dtype)
        which = idx // self.block_rows
        for b in np.unique(which):
            start = int(b) * self.block_rows
            sel = np.flatnonzero(which == b)
            out[sel] = self.rows(start, min(self.shape[0], start + self.block_rows))[
                idx[sel] - start
            ]
        return out


def _h5py() -> Any:
    faiss_module()  # same extra: a clear install hint when missing
    import h5py  # the index extra; ~0.2 s to import

    return h5py


def storage_dtype(method: Method, array: np.ndarray | RowBlocks, precision: Precision) -> np.dtype:
    """The dtype ``array`` is stored in (see the module docstring)."""
    if isinstance(array, RowBlocks):
        return _blocks_dtype(method, array, precision)
    a = np.asarray(array)
    if a.dtype.kind != "f" or a.dtype == np.float16 or a.size == 0:
        return a.dtype
    if not np.isfinite(a).all() or float(np.abs(a).max()) > _F16_MAX:
        return a.dtype
    if precision == "compact" and getattr(type(method), "index_float16", True) is not False:
        return np.dtype(np.float16)
    half = a.astype(np.float16)
    return np.dtype(np.float16) if np.array_equal(half.astype(a.dtype), a) else a.dtype


def _blocks_dtype(method: Method, rows: RowBlocks, precision: Precision) -> np.dtype:
    """:func:`storage_dtype` of rows given block by block: the same decision, one block at a
    time (stopping at the first block that keeps the rows' own dtype)."""
    dtype = rows.dtype
    if dtype.kind != "f" or dtype == np.float16 or rows.size == 0:
        return dtype
    compact = precision == "compact" and getattr(type(method), "index_float16", True) is not False
    for _, a in rows.blocks():
        if not np.isfinite(a).all() or float(np.abs(a).max()) > _F16_MAX:
            return dtype
        if not compact and not np.array_equal(a.astype(np.float16).astype(dtype), a):
            return dtype
    return np.dtype(np.float16)


def _put(group: Any, name: str, array: np.ndarray | RowBlocks, dtype: np.dtype) -> int:
    if isinstance(array, RowBlocks):  # the same contiguous dataset, written block by block
        ds = group.create_dataset(name, shape=array.shape, dtype=dtype)
        for start, block in array.blocks():
            ds[start : start + len(block)] = block.astype(dtype, copy=False)
        ds.attrs["dtype"] = array.dtype.str
        return int(ds.id.get_storage_size())
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
    globals_: Mapping[str, np.ndarray | RowBlocks],
    methods: Mapping[str, Method],
    precision: Precision,
) -> dict[str, int]:
    """Write ``references.h5``; returns bytes stored per global method id (a matrix may be
    :class:`RowBlocks`)."""
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
    locals_: Mapping[str, Mapping[str, Ragged | RowBlocks]],
    methods: Mapping[str, Method],
    precision: Precision,
) -> dict[str, int]:
    """Write ``local.h5``; returns bytes stored per local method id (an array may be
    :class:`RowBlocks` ``(N, n, ...)``: ``n`` rows per image, the equal-count layout)."""
    h5py = _h5py()
    sizes: dict[str, int] = {}
    with h5py.File(path, "w", libver="latest") as f:
        root = f.create_group("local")
        for mid, arrays in locals_.items():
            g = root.create_group(mid)
            total = 0
            for key, rag in arrays.items():
                sub = g.create_group(key)
                if isinstance(rag, RowBlocks):
                    sub.attrs["scalar"] = False
                    dtype = storage_dtype(methods[mid], rag, precision)
                    total += _put(sub, "blocks", rag, dtype)
                    continue
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


def write_profile(path: Path, profile: ReferenceProfile, extra_attrs: Mapping[str, Any]) -> None:
    """Write ``profile.h5``: a :class:`~hmpf.confidence.ReferenceProfile` in float64, so
    :func:`read_profile` restores it bit for bit; ``extra_attrs`` (the parameters it was built
    with: ``sample``, ``window``, ``seed``) are stored as attributes beside ``methods`` and
    ``sign``."""
    h5py = _h5py()
    arrays = profile.to_arrays()
    with h5py.File(path, "w", libver="latest") as f:
        f.attrs["methods"] = json.dumps(list(profile.methods))
        f.attrs["sign"] = arrays["sign"]
        for k, v in extra_attrs.items():
            f.attrs[k] = v
        for k in ("mean", "std"):
            f.create_dataset(k, data=arrays[k])


def read_profile(path: Path) -> ReferenceProfile:
    """The :class:`~hmpf.confidence.ReferenceProfile` :func:`write_profile` wrote.

    Raises:
        IndexCorruptError: naming the file: missing, unreadable, or not a whole profile
            (an attribute or dataset missing, shapes that disagree).
    """
    with open_h5(path) as f:
        try:
            methods = json.loads(f.attrs["methods"])
            if not isinstance(methods, list):
                raise ValueError("attribute methods is not a list")
            arrays = {"sign": np.asarray(f.attrs["sign"]).reshape(-1)}
            arrays.update({k: np.asarray(f[k][()]) for k in ("mean", "std")})
            return ReferenceProfile.from_arrays(methods, arrays)
        except (KeyError, ValueError, TypeError, OSError, HmpfError) as exc:
            raise IndexCorruptError(
                f"{path}: not a readable reference profile ({exc}); run `hmpf-index verify`"
            ) from None


def stored_profile(
    version_dir: Path, manifest: Mapping[str, Any], methods: Sequence[str], n: int
) -> ReferenceProfile | None:
    """The reference profile a version stores (its manifest's ``profile`` entry), checked
    against what a reader of it would build: the profiled ``methods`` (tier 1's global
    methods, in order) over ``n`` places.

    Returns:
        the profile; None where the version stores none (written before versions stored
        it) or one built with other parameters than this hmpf's
        (:func:`hmpf.confidence.profile_params`): the caller builds it.

    Raises:
        IndexCorruptError: naming the file: an entry whose file the manifest's checksums do
            not cover, an unreadable file, or a profile of other methods or another number
            of places than the version's.
    """
    entry = manifest.get("profile")
    if entry is None:
        return None
    name = entry.get("file") if isinstance(entry, Mapping) else None
    if not isinstance(name, str) or name not in manifest.get("files", {}):
        raise IndexCorruptError(
            f"{version_dir / layout.MANIFEST}: profile entry {entry!r} names no file of the "
            "version; run `hmpf-index verify`"
        )
    if entry.get("params") != profile_params():
        log.info(
            "%s: stored reference profile built with %s, this hmpf builds %s: building it anew",
            version_dir,
            entry.get("params"),
            profile_params(),
        )
        return None
    path = version_dir / name
    profile = read_profile(path)
    if list(profile.methods) != list(methods) or profile.n != n:
        raise IndexCorruptError(
            f"{path}: a profile of methods {list(profile.methods)} over {profile.n} places, "
            f"the version has {list(methods)} over {n}; run `hmpf-index verify`"
        )
    return profile
