"""Feature extraction over image lists, in parallel processes, with an on-disk cache.

The cache is keyed by the method's :meth:`~hmpf.methods.base.Method.descriptor_key` (name,
code version, config, CNN runtime) and by the sha256 of the image file's bytes, so a second
run re-extracts nothing and a change to either the method or the image invalidates the entry.
Entries are ``.npz`` files written atomically (temporary file + rename); a corrupt entry is
re-extracted.

How a method is run is what it declares (:mod:`hmpf.methods.base`), never its type: ``batched``
methods (the CNNs) run in this process ``batch_size`` images at a time, the others image by
image in worker processes; methods with equal ``group_key()`` share one pass per image (one CNN
forward pass); methods whose ``requires_fit()`` is True are fitted first (:func:`fit_methods`).
"""

from __future__ import annotations

import hashlib
import io
import json
import multiprocessing
import os
import threading
import time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from hmpf.imageio import load_image
from hmpf.methods import Method
from hmpf.methods.base import extract_many, fit_many, method_groups
from hmpf.runtime import default_cache_dir, ignore_sigint, set_compute_threads

__all__ = [
    "ExtractionResult",
    "FeatureCache",
    "default_cache_dir",
    "extract_images",
    "extract_query",
    "file_digest",
    "fit_methods",
    "pack_features",
    "unpack_features",
]


def file_digest(path: str | os.PathLike[str]) -> str:
    """sha256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class FeatureCache:
    """Per-image, per-method feature files under ``root/<method key>/<sha[:2]>/<sha>.npz``."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    def _path(self, method: Method, digest: str) -> Path:
        return self.root / method.descriptor_key() / digest[:2] / f"{digest}.npz"

    def get(self, method: Method, digest: str) -> tuple[Any, float] | None:
        """(feature, extraction ms when it was computed) or None."""
        p = self._path(method, digest)
        if not p.exists():
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError):
            return None  # corrupt or partial entry: recompute
        ms = float(arrays.pop("__ms__", np.nan))
        return method.from_arrays(arrays), ms

    def _state_path(self, method_key: str, fit_key: str) -> Path:
        return self.root / "fitted" / method_key / f"{fit_key}.npz"

    def get_state(self, method_key: str, fit_key: str) -> dict[str, np.ndarray] | None:
        """Fitted parameters of the unfitted method ``method_key`` (its
        ``descriptor_key()``) for the fitting image set ``fit_key``, or None."""
        p = self._state_path(method_key, fit_key)
        try:
            with np.load(p, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError):
            return None

    def put_state(self, method_key: str, fit_key: str, state: dict[str, np.ndarray]) -> None:
        p = self._state_path(method_key, fit_key)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            # mypy matches **dict[str, ndarray] against savez's allow_pickle: bool keyword.
            np.savez(fh, **state)  # type: ignore[arg-type]
        os.replace(tmp, p)

    def put(self, method: Method, digest: str, feature: Any, ms: float) -> None:
        p = self._path(method, digest)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, __ms__=np.float64(ms), **method.to_arrays(feature))  # type: ignore[arg-type]
        os.replace(tmp, p)


@dataclass
class ExtractionResult:
    """Features of every image per method id, plus per-image extraction times (ms).

    ``ms[mid]`` holds the time measured when each feature was computed (this run or the run
    that filled the cache); ``cached[mid]`` counts the images taken from the cache.
    """

    features: dict[str, list[Any]]
    ms: dict[str, np.ndarray]
    cached: dict[str, int] = field(default_factory=dict)
    decode_ms: float = float("nan")


_WORKER_METHODS: dict[str, Method] = {}


def _init_worker(methods: Mapping[str, Method], single_thread: bool = True) -> None:
    if single_thread:
        set_compute_threads(1)
    _WORKER_METHODS.clear()
    _WORKER_METHODS.update(methods)


def _init_pool_worker(methods: Mapping[str, Method], lifeline: Connection) -> None:
    ignore_sigint()  # Ctrl-C is the parent's: a worker stops without a traceback
    _exit_with_parent(lifeline)
    _init_worker(methods)


def _exit_with_parent(lifeline: Connection) -> None:
    """End this worker as soon as the process that started its pool is gone, killed or not.

    ``lifeline`` is the read end of a pipe whose only write end that process holds (never
    written to): its end of file means the parent has exited. A thread of the worker waits
    for it. Without this a worker whose parent was killed (SIGKILL: no pool shutdown) waits
    for work for ever, and keeps the forkserver and the resource tracker alive with it (they
    exit once no worker holds their pipes). A parent-death signal (``PR_SET_PDEATHSIG``)
    would not do: a forkserver worker's parent is the forkserver, not the pool's owner.
    """

    def watch() -> None:
        try:
            lifeline.recv_bytes()  # nothing is ever sent: returns only at end of file
        except (EOFError, OSError):
            pass
        os._exit(1)

    threading.Thread(target=watch, name="hmpf-parent-watch", daemon=True).start()


def _extract_one(
    path: str, method_ids: Sequence[str]
) -> tuple[dict[str, Any], dict[str, float], float]:
    """One image's features of the worker's methods ``method_ids`` (image by image)."""
    t0 = time.perf_counter()
    image = load_image(path)
    decode_ms = (time.perf_counter() - t0) * 1e3
    times: dict[str, list[float]] = {}
    feats = extract_many({mid: _WORKER_METHODS[mid] for mid in method_ids}, [image], times)
    return (
        {mid: f[0] for mid, f in feats.items()},
        {mid: t[0] for mid, t in times.items()},
        decode_ms,
    )


#: The member of a packed feature set (:func:`pack_features`) that names its methods.
_PACKED_KEYS = "__methods__"


def pack_features(methods: Mapping[str, Method], features: Mapping[str, Any]) -> bytes:
    """One image's features (``methods``' ids -> feature, as :func:`extract_query` returns
    them) as ``.npz`` bytes: each method's arrays (:meth:`~hmpf.methods.base.Method.to_arrays`)
    under ``<id>/<name>``, and the methods' :meth:`~hmpf.methods.base.Method.descriptor_key`
    (code version, parameters, fitted state, CNN runtime), so that they are only ever read
    back by the same methods (:func:`unpack_features`)."""
    arrays: dict[str, np.ndarray] = {}
    for mid, method in methods.items():
        for name, value in method.to_arrays(features[mid]).items():
            arrays[f"{mid}/{name}"] = np.asarray(value)
    keys = {mid: m.descriptor_key() for mid, m in methods.items()}
    arrays[_PACKED_KEYS] = np.frombuffer(json.dumps(keys, sort_keys=True).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def unpack_features(methods: Mapping[str, Method], data: bytes) -> dict[str, Any] | None:
    """The features :func:`pack_features` packed, when they were packed by exactly these
    ``methods`` (the same ids and descriptor keys); None otherwise, or when ``data`` does not
    read (the caller extracts them from the image instead)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        keys = json.loads(arrays.pop(_PACKED_KEYS).tobytes().decode())
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, UnicodeDecodeError):
        return None
    if keys != {mid: m.descriptor_key() for mid, m in methods.items()}:
        return None
    out: dict[str, Any] = {}
    for mid, method in methods.items():
        prefix = f"{mid}/"
        own = {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}
        try:
            out[mid] = method.from_arrays(own)
        except (KeyError, ValueError, TypeError):
            return None
    return out


def extract_query(
    methods: Mapping[str, Method],
    image: np.ndarray,
    ms: dict[str, float] | None = None,
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Every method's feature of one decoded image.

    Methods sharing a :meth:`~hmpf.methods.base.Method.group_key` (CNN methods on one
    backbone and input size) share one forward pass. Without ``executor`` everything runs in
    the calling thread; with one, each group is a task on it, so one query can use several
    cores while the executor's size bounds the whole process's compute. When ``ms`` is given,
    each method's time (ms) is stored in it; a group's shared pass is counted once, in its
    first method.
    """
    tasks: list[Callable[[], tuple[dict[str, Any], dict[str, float]]]] = [
        partial(_extract_group_once, group, image) for group in method_groups(methods)
    ]
    if executor is None or len(tasks) < 2:
        results = [task() for task in tasks]
    else:
        results = [f.result() for f in [executor.submit(task) for task in tasks]]
    out: dict[str, Any] = {}
    for feats, times in results:
        out.update(feats)
        if ms is not None:
            ms.update(times)
    return {mid: out[mid] for mid in methods}


def _extract_group_once(
    group: Mapping[str, Method], image: np.ndarray
) -> tuple[dict[str, Any], dict[str, float]]:
    """One image's features of one group and per-method times (shared time in the first)."""
    res = type(next(iter(group.values()))).extract_group(group, [image])
    feats = {mid: f[0] for mid, f in res.features.items()}
    times = {
        mid: own[0] + (res.shared_ms[0] if j == 0 else 0.0)
        for j, (mid, own) in enumerate(res.own_ms.items())
    }
    return feats, times


def _extract_batched(
    paths: Sequence[str | os.PathLike[str]],
    todo: Mapping[int, Sequence[str]],
    methods: Mapping[str, Method],
    store: Callable[[int, str, Any, float], None],
    progress: bool,
) -> None:
    """Batched methods in this process, ``batch_size`` images at a time (torch uses every
    core for one batch). ``todo``: image index -> the batched methods it lacks; an image
    runs only those (a feature already cached is not computed again), images lacking the
    same methods batched together."""
    alike: dict[tuple[str, ...], list[int]] = {}
    for i in sorted(todo):
        alike.setdefault(tuple(m for m in methods if m in todo[i]), []).append(i)
    bar = tqdm(total=len(todo), desc="cnn", unit="img", disable=None if progress else True)
    try:
        for mids, todo_i in alike.items():
            run = {m: methods[m] for m in mids}
            chunk = max(m.batch_size for m in run.values())
            for start in range(0, len(todo_i), chunk):
                idx = todo_i[start : start + chunk]
                images = [load_image(paths[i]) for i in idx]
                times: dict[str, list[float]] = {}
                feats = extract_many(run, images, times)
                for mid, fs in feats.items():
                    for j, i in enumerate(idx):
                        store(i, mid, fs[j], times[mid][j])
                bar.update(len(idx))
    finally:
        bar.close()


def fit_methods(
    methods: Mapping[str, Method],
    paths: Sequence[str | os.PathLike[str]],
    *,
    cache: FeatureCache | None = None,
    max_images: int = 500,
) -> list[str]:
    """Fit (in place) the methods whose ``requires_fit()`` is True on reference images.

    Uses up to ``max_images`` references, evenly spaced along the list (deterministic). With a
    cache, parameters fitted before on the same images (by content) are loaded instead, and
    the features a fit computes on the way (:func:`~hmpf.methods.base.fit_many`) are stored
    in it, so that extracting those references afterwards reads them instead of running the
    same forward passes again.

    Returns:
        The ids of the methods that needed fitting.
    """
    todo = {mid: m for mid, m in methods.items() if m.requires_fit()}
    if not todo or not paths:
        return []
    n = len(paths)
    pick = np.unique(np.linspace(0, n - 1, min(n, max_images)).round().astype(np.int64))
    fit_key = ""
    digests: list[str] = []
    if cache is not None:
        digests = [file_digest(paths[i]) for i in pick]
        fit_key = hashlib.sha256("".join(digests).encode()).hexdigest()[:32]
    pending: dict[str, Method] = {}
    for mid, m in todo.items():
        state = cache.get_state(m.descriptor_key(), fit_key) if cache is not None else None
        if state is not None:
            m.load_state(state)
        else:
            pending[mid] = m
    if pending:
        keys = {mid: m.descriptor_key() for mid, m in pending.items()}  # before fitting
        images = [load_image(paths[i]) for i in pick]
        seen = fit_many(pending, images)
        if cache is not None:
            for mid, m in pending.items():
                cache.put_state(keys[mid], fit_key, m.state_arrays())
            for mid, (feats, ms) in seen.items():
                for digest, f, t_ms in zip(digests, feats, ms, strict=True):
                    cache.put(pending[mid], digest, f, t_ms)
    return list(todo)


def extract_images(
    paths: Sequence[str | os.PathLike[str]],
    methods: Mapping[str, Method],
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    progress: bool = False,
    desc: str = "extract",
) -> ExtractionResult:
    """Extract every method's feature for every image (cached ones are loaded, not recomputed).

    The cache wraps the one extraction path: hits are loaded, the misses extracted, and each
    new feature written to the cache as it arrives.

    Args:
        paths: image files.
        methods: method id -> instance.
        cache: feature cache, or None to always extract.
        workers: processes (default: CPU count; 1 runs in this process).
        progress: show a progress bar with images/s and ETA on stderr.

    Raises:
        ImageError: an image cannot be read (the message names it).
    """
    n = len(paths)
    ids = list(methods)
    features: dict[str, list[Any]] = {m: [None] * n for m in ids}
    ms: dict[str, np.ndarray] = {m: np.full(n, np.nan) for m in ids}
    cached = {m: 0 for m in ids}
    todo: dict[int, list[str]] = {}
    digests = [file_digest(p) for p in paths] if cache is not None else [""] * n
    for i in range(n):
        for mid in ids:
            hit = cache.get(methods[mid], digests[i]) if cache is not None else None
            if hit is None:
                todo.setdefault(i, []).append(mid)
            else:
                features[mid][i], ms[mid][i] = hit
                cached[mid] += 1

    def store(i: int, mid: str, f: Any, t_ms: float) -> None:
        features[mid][i] = f
        ms[mid][i] = t_ms
        if cache is not None:
            cache.put(methods[mid], digests[i], f, t_ms)

    decode = _extract(paths, methods, todo, store, workers=workers, progress=progress, desc=desc)
    return ExtractionResult(
        features, ms, cached, float(np.median(decode)) if decode else float("nan")
    )


def _extract(
    paths: Sequence[str | os.PathLike[str]],
    methods: Mapping[str, Method],
    todo: Mapping[int, Sequence[str]],
    store: Callable[[int, str, Any, float], None],
    *,
    workers: int | None,
    progress: bool,
    desc: str,
) -> list[float]:
    """Extract ``todo`` (image index -> method ids), handing each feature to ``store``.

    Batched methods run here, ``batch_size`` images at a time; the others image by image, in
    ``workers`` processes.

    Returns:
        The decode time (ms) of each image the worker path read.
    """
    decode: list[float] = []
    batched_ids = [m for m in methods if methods[m].batched]
    batched_todo = {i: [m for m in mids if m in batched_ids] for i, mids in todo.items()}
    batched_todo = {i: mids for i, mids in batched_todo.items() if mids}
    cpu_todo = {i: [m for m in mids if m not in batched_ids] for i, mids in todo.items()}
    cpu_todo = {i: mids for i, mids in cpu_todo.items() if mids}
    if batched_todo:
        batched = {m: methods[m] for m in batched_ids}
        _extract_batched(paths, batched_todo, batched, store, progress)
    jobs = sorted(cpu_todo)
    if not jobs:
        return decode
    n_workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    bar = tqdm(total=len(jobs), desc=desc, unit="img", disable=None if progress else True)
    closing: list[Connection] = []

    def collect(i: int, res: tuple[dict[str, Any], dict[str, float], float]) -> None:
        feats, times, dms = res
        decode.append(dms)
        for mid, f in feats.items():
            store(i, mid, f, times[mid])
        bar.update(1)

    try:
        if n_workers == 1:
            _init_worker(methods, single_thread=False)
            for i in jobs:
                collect(i, _extract_one(str(paths[i]), cpu_todo[i]))
        else:
            # forkserver: forking a process whose OpenCV/BLAS threads hold locks deadlocks.
            ctx = multiprocessing.get_context("forkserver")
            cpu_methods = {m: methods[m] for m in methods if m not in batched_ids}
            # The workers end when this end of the pipe closes (_exit_with_parent).
            lifeline, alive = ctx.Pipe(duplex=False)
            closing.extend((lifeline, alive))
            with ProcessPoolExecutor(
                n_workers,
                mp_context=ctx,
                initializer=_init_pool_worker,
                initargs=(cpu_methods, lifeline),
            ) as pool:
                futs = {i: pool.submit(_extract_one, str(paths[i]), cpu_todo[i]) for i in jobs}
                try:
                    for i in jobs:
                        collect(i, futs[i].result())
                except BaseException:
                    # Drop the queued images and let each worker finish the one it holds (they
                    # ignore Ctrl-C): a worker ended mid-image could leave half a result in
                    # the pool's result pipe, and the pool's reader thread, joined at exit,
                    # would wait for the rest for ever. A second Ctrl-C waits again (the
                    # pool's exit joins the same thread).
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise
    finally:
        bar.close()
        # Only now, with the pool shut down, may the lifeline close (_exit_with_parent ends
        # any worker still there: only after repeated Ctrl-C).
        for conn in closing:
            conn.close()
    return decode
