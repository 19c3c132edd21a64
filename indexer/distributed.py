"""Extraction of an index build on a Ray cluster (``hmpf-index build|add ... --ray [ADDRESS]``).

Only extraction is distributed; everything else is the local build's code path
(:mod:`indexer.build`): the driver fits the methods that need it (VLAD centroids, OLO
vocabulary) on the references as before, then a Ray Data pipeline runs the images not yet in
the work folder's :class:`~hmpf.features.FeatureCache` through ``map_batches`` on a pool of
actors. Each actor rebuilds the fitted methods once (they pickle with their state,
:meth:`hmpf.methods.base.Method.__reduce__`), uses one compute thread and the driver's CNN
runtime, as a local build's worker processes do, and returns each image's features as
serialised arrays. The driver streams the results (``iter_batches``: nothing is collected) and
writes each one into the feature cache as it arrives; the local path then reads every feature
from that cache and writes, checks and publishes the version exactly as a local build, under
the same writer lock and with the same manifest.

Faults: Ray restarts an actor whose process dies and retries its batch (Ray Data's actor
pools default to ``max_restarts=-1``, ``max_task_retries=-1``: without limit); a feature is
only written by the driver, whole, so a retried batch changes nothing. A killed driver leaves
``CURRENT`` untouched; ``--resume`` (with or without ``--ray``) reuses every feature already
in the cache.

Ray is an optional extra (``pip install 'hmpf[ray]'``); it is imported only here, on use.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import pickle
import socket
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from tqdm import tqdm

from hmpf.errors import HmpfError, ImageError
from hmpf.features import FeatureCache, file_digest
from hmpf.imageio import load_image
from hmpf.index import layout
from hmpf.index.layout import IndexBuildError
from hmpf.methods import Method
from hmpf.methods.base import extract_many
from hmpf.runtime import cnn_runtime, set_cnn_runtime, set_compute_threads

__all__ = [
    "RAY_HINT",
    "RayOptions",
    "VersionMismatchError",
    "extract_to_cache",
    "ray_session",
    "require_ray",
]

RAY_HINT = "--ray needs Ray, an optional extra: pip install 'hmpf[ray]'"


@dataclass(frozen=True)
class RayOptions:
    """Where and how wide extraction runs on Ray.

    Attributes:
        address: an existing cluster's address (``HOST:PORT``, or ``auto``), or None to start
            a local Ray instance for this build.
        workers: extraction actors (one CPU each); default: ``--workers`` or every CPU of the
            cluster.
        batch_size: images per actor task (results stream back a batch at a time).
    """

    address: str | None = None
    workers: int | None = None
    batch_size: int = 4


def require_ray() -> Any:
    """The ``ray`` module (with Ray Data).

    Raises:
        IndexBuildError: Ray is not installed (one line: how to install it).
    """
    try:
        import ray  # the ray extra
        import ray.data  # noqa: F401
    except ImportError:
        raise IndexBuildError(RAY_HINT) from None
    return ray


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Fail fast on a ``HOST:PORT`` nothing listens on (``ray.init`` would retry for minutes)."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise IndexBuildError(f"--ray {address!r}: expected HOST:PORT (or auto)")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise IndexBuildError(
            f"--ray {address}: no Ray cluster reachable there ({exc.strerror or exc}); start "
            "one (ray start --head) or give its address as printed by ray start"
        ) from None


def _package_versions() -> dict[str, str]:
    """What must be equal on the driver and every worker: the recorded package versions
    (manifest ``packages``: hmpf, numpy, OpenCV, torch, ...), ONNX Runtime and OpenVINO
    (the CNN runtimes)."""
    out = layout.package_versions()
    for runtime in ("onnxruntime", "openvino"):
        version = layout.installed_version(runtime)
        if version is not None:
            out[runtime] = version
    return out


@contextlib.contextmanager
def ray_session(opt: RayOptions) -> Iterator[int]:
    """Connect to ``opt.address`` (or start a local instance); yields the number of actors.

    The driver disconnects on exit; a local instance stops with it.
    """
    ray = require_ray()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if ray.is_initialized():  # e.g. a test or notebook already connected: use that
        owned = False
    else:
        owned = True
        kwargs: dict[str, Any] = {
            "include_dashboard": False,
            "log_to_driver": False,
            "logging_level": "WARNING",
            "configure_logging": True,
        }
        if opt.address is None:  # a new instance, even where RAY_ADDRESS names a cluster
            kwargs["address"] = "local"
            kwargs["num_cpus"] = opt.workers or os.cpu_count() or 1
        else:
            if opt.address != "auto":
                _check_reachable(opt.address)
            kwargs["address"] = opt.address
        try:
            ray.init(**kwargs)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = opt.address or "a local instance"
            raise IndexBuildError(f"--ray: cannot start or reach {where}: {exc}") from None
    try:
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if cpus < 1:
            raise IndexBuildError("--ray: the Ray cluster has no CPU to run extraction on")
        yield max(1, min(opt.workers or cpus, cpus))
    finally:
        if owned:
            ray.shutdown()


class VersionMismatchError(IndexBuildError):
    """A worker's packages differ from the driver's (features could differ)."""


class _Extractor:
    """A Ray Data actor: the fitted methods, rebuilt once; extracts batches of images.

    Same settings as a local build's worker process (``hmpf.features._init_worker``): one
    compute thread, the driver's CNN runtime, so features are the same bits. Used through a
    subclass holding the methods (:func:`_extractor_class`).
    """

    #: the methods, pickled with their fitted state, the CNN runtime and the driver's
    #: package versions
    blob: ClassVar[bytes] = b""
    runtime: ClassVar[str] = "onnx"
    versions: ClassVar[dict[str, str]] = {}

    def __init__(self) -> None:
        mine = _package_versions()
        if mine != self.versions:
            keys = {*mine, *self.versions}
            differ = sorted(k for k in keys if mine.get(k) != self.versions.get(k))
            raise VersionMismatchError(
                f"worker node {socket.gethostname()} has other package versions than the "
                "driver: "
                + ", ".join(
                    f"{k} {mine.get(k, 'missing')} (driver {self.versions.get(k, 'missing')})"
                    for k in differ
                )
                + "; install the same hmpf and packages on every node"
            )
        set_compute_threads(1)
        set_cnn_runtime(self.runtime)
        self.methods: dict[str, Method] = pickle.loads(self.blob)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        rows: dict[str, list[Any]] = {"i": [], "mid": [], "npz": []}
        groups: dict[str, list[int]] = {}
        for j, mids in enumerate(batch["mids"]):
            groups.setdefault(str(mids), []).append(j)
        for mids, js in groups.items():
            images = [load_image(str(batch["path"][j])) for j in js]
            todo = {mid: self.methods[mid] for mid in mids.split(",")}
            times: dict[str, list[float]] = {}
            feats = extract_many(todo, images, times)
            for mid, fs in feats.items():
                for k, j in enumerate(js):
                    rows["i"].append(int(batch["i"][j]))
                    rows["mid"].append(mid)
                    rows["npz"].append(_pack(todo[mid], fs[k], times[mid][k]))
        return {
            "i": np.asarray(rows["i"], dtype=np.int64),
            "mid": np.asarray(rows["mid"], dtype=object),
            "npz": np.asarray(rows["npz"], dtype=object),
        }


def _extractor_class(methods: Mapping[str, Method], runtime: str) -> type[_Extractor]:
    """An :class:`_Extractor` subclass carrying ``methods`` (with their fitted state) and
    ``runtime``: Ray ships the class by value with the actor's definition, so a restarted actor
    rebuilds from it (constructor arguments would live in the object store, and a restart
    fails once they are lost)."""
    attrs = {
        "blob": pickle.dumps(dict(methods)),
        "runtime": runtime,
        "versions": _package_versions(),
    }
    return type("_FittedExtractor", (_Extractor,), attrs)


def _pack(method: Method, feature: Any, ms: float) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, __ms__=np.float64(ms), **method.to_arrays(feature))  # type: ignore[arg-type]
    return buf.getvalue()


def _unpack(method: Method, data: bytes) -> tuple[Any, float]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    ms = float(arrays.pop("__ms__"))
    return method.from_arrays(arrays), ms


def _todo(
    paths: Sequence[Path], methods: Mapping[str, Method], cache: FeatureCache
) -> tuple[list[dict[str, Any]], list[str], int]:
    """Rows (index, absolute path, missing method ids) of the images to extract, every
    image's digest, and how many images were complete already."""
    rows: list[dict[str, Any]] = []
    digests = [file_digest(p) for p in paths]
    for i, (p, d) in enumerate(zip(paths, digests, strict=True)):
        missing = [mid for mid, m in methods.items() if cache.get(m, d) is None]
        if missing:
            rows.append({"i": i, "path": str(Path(p).resolve()), "mids": ",".join(missing)})
    return rows, digests, len(paths) - len(rows)


def _cause(exc: BaseException, kind: type[HmpfError]) -> HmpfError | None:
    """The ``kind`` exception a worker raised, from the exceptions Ray wraps it in: the object
    itself where Ray keeps it, else rebuilt from its last line in Ray's message (an actor that
    died in its constructor leaves only the traceback text)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, kind):
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or getattr(cur, "cause", None) or cur.__context__
    if kind is VersionMismatchError:
        tag = f"{kind.__module__}.{kind.__name__}: "
        lines = [ln.strip() for ln in str(exc).splitlines() if tag in ln]
        return kind(lines[-1].split(tag, 1)[1]) if lines else None
    return None


def extract_to_cache(
    paths: Sequence[Path],
    methods: Mapping[str, Method],
    cache: FeatureCache,
    opt: RayOptions,
    *,
    progress: bool = False,
) -> int:
    """Extract on Ray every feature of ``methods`` for ``paths`` missing from ``cache`` and
    write each into ``cache`` as it arrives (driver memory: one batch at a time).

    Returns:
        How many images were complete in the cache before (resumed).

    Raises:
        IndexBuildError: Ray is missing or unreachable, or extraction failed on the cluster.
        ImageError: a worker could not read an image.
    """
    rows, digests, done = _todo(paths, methods, cache)
    if not rows:
        return done
    with ray_session(opt) as n_actors:
        ray = require_ray()
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False
        ctx.print_on_execution_start = False
        logging.getLogger("ray.data").setLevel(logging.WARNING)
        batch = max(1, opt.batch_size)
        n_actors = max(1, min(n_actors, -(-len(rows) // batch)))
        ds = ray.data.from_items(rows, override_num_blocks=max(1, -(-len(rows) // batch)))
        ds = ds.map_batches(
            _extractor_class(methods, cnn_runtime()),
            batch_size=batch,
            batch_format="numpy",
            compute=ray.data.ActorPoolStrategy(size=n_actors),
            num_cpus=1,
        )
        bar = tqdm(
            total=len(rows), desc="extract (ray)", unit="img", disable=None if progress else True
        )
        left = {r["i"]: len(r["mids"].split(",")) for r in rows}
        try:
            for out in ds.iter_batches(batch_size=None, batch_format="numpy"):
                for i, mid, data in zip(out["i"], out["mid"], out["npz"], strict=True):
                    m = methods[str(mid)]
                    feature, ms = _unpack(m, bytes(data))
                    cache.put(m, digests[int(i)], feature, ms)
                    left[int(i)] -= 1
                    if left[int(i)] == 0:
                        bar.update(1)
        except Exception as exc:
            for kind in (ImageError, VersionMismatchError):
                cause = _cause(exc, kind)
                if cause is not None:
                    raise cause from None
            if isinstance(exc, IndexBuildError):
                raise
            raise IndexBuildError(
                f"--ray: extraction failed on the cluster: {type(exc).__name__}: "
                f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else ''} (finished "
                "images are kept; rerun with --resume)"
            ) from exc
        finally:
            bar.close()
    missing = sum(n > 0 for n in left.values())
    if missing:  # Ray Data retries lost batches; never expected, but never hidden either
        raise IndexBuildError(
            f"--ray: the cluster returned no features for {missing} image(s); rerun with --resume"
        )
    return done
