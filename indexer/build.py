"""``build``, ``add`` and ``remove``: each writes a new immutable version and publishes it.

Every operation is a :class:`VersionTransaction`: it holds the index's writer lock, works in
``INDEX/.build/`` and ends by publishing a :class:`NewVersion` (data files, manifest with
checksums, fsync, rename, ``CURRENT``). The work folder holds:

* ``job.json``   what the operation is (config hash, images and their sha256, options), so
  that ``--resume`` continues only the same job;
* ``features/``  one file per image and method, written as soon as the image is done
  (:class:`hmpf.features.FeatureCache`): a resumed job extracts only the missing images;
* ``state.h5``   fitted parameters, saved before extraction (a resumed job reuses them);
* ``out/``       the version being written; fsynced, renamed to ``vNNNN``, then ``CURRENT``
  is switched atomically and ``.build`` deleted.

An interruption at any point (Ctrl-C, kill -9, full disk) leaves ``CURRENT`` and every
published version untouched.

A version may hold fleet *experiences* (:mod:`indexer.experiences`): its rows are the places'
original references first, then experience rows whose ``place`` column names their place
(:data:`hmpf.index.tables.EXPERIENCE_COLUMNS`). ``add`` inserts new places before the
experience rows and ``remove`` of a place removes its experiences and renumbers the places, so
every version keeps that order; :func:`check_places` refuses to publish one that does not.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import platform
import shutil
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

import hmpf.features as hfeatures
from hmpf.confidence import profile_params
from hmpf.config import HierarchyConfig, build_methods, load_config, with_shipped_acceptance
from hmpf.errors import ImageError
from hmpf.evaluation.auto import choose_config, map_prior_or_why
from hmpf.features import FeatureCache, extract_images, file_digest
from hmpf.index import layout, thumbnails
from hmpf.index.ann import (
    MetricSpec,
    build_faiss,
    declared_metric,
    faiss_module,
    is_exact_factory,
    read_faiss,
    set_search_params,
)
from hmpf.index.layout import IndexBuildError, IndexCorruptError
from hmpf.index.models import MODELS_DIR, write_models
from hmpf.index.places import Places, augment_rows, augments, places_profile, route_map_of
from hmpf.index.reader import IndexReader
from hmpf.index.rows import DiskRows, disk_rows
from hmpf.index.storage import (
    Precision,
    RowBlocks,
    open_h5,
    read_global,
    read_ref_table,
    read_state,
    write_local,
    write_profile,
    write_references,
    write_state,
)
from hmpf.index.tables import (
    EXPERIENCE_COLUMNS,
    Columns,
    Ragged,
    RefTable,
    columns_from_features,
    concat_columns,
    select_columns,
)
from hmpf.index.thumbnails import empty_thumbnails
from hmpf.methods import Method
from indexer.distributed import RayOptions, extract_to_cache
from indexer.inputs import ImageCheck, check_images, read_metadata, scan_images

__all__ = [
    "BuildOptions",
    "NewVersion",
    "Summary",
    "VersionTransaction",
    "add",
    "build",
    "check_places",
    "place_count",
    "remove",
]


@dataclass(frozen=True)
class BuildOptions:
    """How versions are written.

    Attributes:
        faiss: tier-1 method id -> FAISS factory string; key ``"*"`` applies to every
            tier-1 global method not named (default ``Flat``: exact).
        faiss_params: method id (or ``"*"``) -> FAISS search parameters, e.g. ``nprobe=16``.
        precision: ``exact`` or ``compact`` (see :mod:`hmpf.index.storage`).
        strict: fail on an unreadable image instead of skipping it.
        workers: extraction processes (default: CPU count).
        progress: progress bars on stderr.
        ray: extract on a Ray cluster (:mod:`indexer.distributed`) instead of local
            processes; not part of the output's identity (the version is the same bits).
    """

    faiss: Mapping[str, str] = field(default_factory=dict)
    faiss_params: Mapping[str, str] = field(default_factory=dict)
    precision: Precision = "exact"
    strict: bool = False
    workers: int | None = None
    progress: bool = True
    ray: RayOptions | None = None

    def with_config(self, config: HierarchyConfig) -> BuildOptions:
        """These options over the config's ``index`` defaults (options win per method id)."""
        return replace(
            self,
            faiss={**config.index.faiss, **self.faiss},
            faiss_params={**config.index.faiss_params, **self.faiss_params},
        )

    def factory(self, mid: str) -> str:
        return self.faiss.get(mid, self.faiss.get("*", "Flat"))

    def params(self, mid: str) -> str:
        return self.faiss_params.get(mid, self.faiss_params.get("*", ""))

    def identity(self) -> dict[str, Any]:
        """The options that change the output (part of a resumable job's identity)."""
        return {
            "faiss": dict(self.faiss),
            "faiss_params": dict(self.faiss_params),
            "precision": self.precision,
            "strict": self.strict,
        }


@dataclass
class Summary:
    """What an operation did (printed by the CLI, also in the manifest)."""

    version: str
    operation: str
    images: int
    extracted: int
    reused: int
    skipped: list[dict[str, str]]
    resumed: int
    seconds: float
    images_per_s: float
    bytes_total: int
    bytes_per_method: dict[str, int]
    #: bytes of the reference thumbnails (``thumbnails.h5``; 0: none stored)
    bytes_thumbnails: int = 0
    #: bytes of the CNN models the version carries (``onnx/``): once per version, whatever
    #: its size, so not counted per reference
    bytes_models: int = 0
    #: what a merge of fleet experiences or their removal did (the manifest's ``experiences``
    #: entry, :mod:`indexer.experiences`); None for other operations
    experiences: dict[str, Any] | None = None
    #: ``--config auto``: what was chosen, why, and how long the choice took (from the
    #: manifest's ``choice``); None for a named config
    choice: dict[str, Any] | None = None
    #: what serving the version will do about the map's prior when its config's acceptance
    #: models read one and the version stores none (:func:`prior_note`); None otherwise
    map_prior_note: str | None = None

    def lines(self) -> list[str]:
        n = max(self.images, 1)
        models = (
            f" (of which CNN models {self.bytes_models / 1e6:.2f} MB, once per version)"
            if self.bytes_models
            else ""
        )
        per_reference = (self.bytes_total - self.bytes_models) / n / 1024
        out = [
            f"{self.operation}: published {self.version} with {self.images} references "
            f"({self.extracted} extracted of which {self.resumed} resumed, {self.reused} reused, "
            f"{len(self.skipped)} skipped) "
            f"in {self.seconds:.1f} s ({self.images_per_s:.1f} images/s)",
            f"on disk: {self.bytes_total / 1e6:.2f} MB{models}, {per_reference:.1f} KiB "
            "per reference; per method: "
            + ", ".join(f"{m} {b / n / 1024:.1f} KiB" for m, b in self.bytes_per_method.items())
            + f"; thumbnails {self.bytes_thumbnails / n / 1024:.1f} KiB",
        ]
        out += [f"skipped {s['name']}: {s['reason']}" for s in self.skipped]
        if self.experiences is not None:
            out += experience_lines(self.experiences)
        if self.choice is not None:
            ch = self.choice
            out.append(
                f"config auto (seed {ch['seed']}, chosen in {ch['time_s']['total_s']:.0f} s "
                "before extraction): "
                f"{ch['chosen']['hierarchy']}, digest {ch['digest'][:12]}: {ch['chosen']['why']}"
            )
        if self.map_prior_note:
            out.append(self.map_prior_note)
        return out


#: How the terminal names a merge's gates (:data:`indexer.experiences.GATES`).
_GATE_LABELS = {
    "already_merged": "already merged",
    "below_p_correct": "below min_p_correct",
    "unknown_place": "unknown place",
    "over_cap": "over max_per_place",
}


def experience_lines(report: Mapping[str, Any]) -> list[str]:
    """A merge's or an experience removal's report (the manifest's ``experiences`` entry) as
    lines for the terminal."""
    places = report.get("places", {})
    tail = f"; now {places.get('count')} places, {places.get('experiences')} experiences"
    if report.get("operation") == "remove":
        return [
            f"removed {report['removed']} experience(s) matching "
            + " and ".join(report["filters"])
            + (tail if places else "")
        ]
    gates = report["gates"]
    lines = [
        f"records {report['records']} from {len(report['logs'])} log(s): "
        + ", ".join(f"{_GATE_LABELS.get(k, k)} {v}" for k, v in gates.items())
        + f"; added {report['added']}"
        + (tail if places else ""),
        f"frames extracted {report['frames_extracted']}, features read from the log "
        f"{report.get('features_recorded', 0)} "
        f"({report['frames_per_s']:.1f} frames/s, extraction, localisation and gates)",
    ]
    if report.get("interpolated"):
        lines.append(
            f"placed between their time neighbours (one place from where recorded): "
            f"{report['interpolated']}"
        )
    if report.get("leads_placed"):
        lines.append(f"lead frames placed from the frames after them: {report['leads_placed']}")
    lines += [f"  {line}" for line in report.get("rejected_agreement", [])]
    return lines


# -- inputs ----------------------------------------------------------------------------------
#: ``build``'s config that asks for the automatic choice (``hmpf-index build --config auto``).
AUTO = "auto"


def _load_config(config: str | Path | HierarchyConfig) -> HierarchyConfig:
    return config if isinstance(config, HierarchyConfig) else load_config(config)


def _check_options(config: HierarchyConfig, methods: Mapping[str, Method], opt: BuildOptions):
    """Refuse, before any image is read, options and tier-1 methods the build cannot honour."""
    tier1 = [m for m in config.tiers[0].methods if methods[m].kind == "global"]
    for what, mapping in (("faiss", opt.faiss), ("faiss-params", opt.faiss_params)):
        bad = [k for k in mapping if k != "*" and k not in tier1]
        if bad:
            raise IndexBuildError(
                f"--{what} names {', '.join(bad)}: not a tier-1 global method of "
                f"{config.name!r} (those are: {', '.join(tier1) or 'none'})"
            )
    for mid in tier1:
        _tier1_metric(mid, methods[mid], opt.factory(mid))


def _tier1_metric(mid: str, method: Method, factory: str) -> MetricSpec | None:
    """The FAISS metric tier-1 global method ``mid`` declares, checked against ``factory``:
    a method without a FAISS metric (None) can only be searched exactly."""
    metric = declared_metric(mid, method)
    if metric is None and not is_exact_factory(factory):
        raise IndexBuildError(
            f"method {mid!r} has no FAISS metric, so it cannot use "
            f"{factory!r}; use Flat (tier 1 then scans the stored matrix)"
        )
    return metric


def _read_inputs(images: str | Path, metadata: str | Path | None) -> tuple[list[Path], RefTable]:
    paths = scan_images(images)
    names = [p.name for p in paths]
    meta = read_metadata(metadata, names) if metadata is not None else {}
    folder = str(Path(images).resolve())
    return paths, RefTable(names, [""] * len(names), meta, [folder] * len(names))


# -- the work folder -------------------------------------------------------------------------
class WorkDir:
    """``INDEX/.build``: a resumable job's persisted progress."""

    def __init__(self, root: Path) -> None:
        self.path = root / layout.BUILD_DIR

    def start(self, job: dict[str, Any], resume: bool) -> bool:
        """Create or reuse the folder; True when a previous run of ``job`` is resumed."""
        job_file = self.path / "job.json"
        if self.path.exists():
            old = _read_json(job_file)
            if resume and old == job:
                return True
            if resume and old is not None:
                raise IndexBuildError(
                    f"{self.path}: the interrupted job differs (operation "
                    f"{old.get('operation')!r}, other images, config or options); rerun "
                    "without --resume to discard it"
                )
            shutil.rmtree(self.path)
        self.path.mkdir(parents=True)
        layout.write_json_atomic(job_file, job)
        return False

    @property
    def cache(self) -> FeatureCache:
        return FeatureCache(self.path / "features")

    @property
    def state(self) -> Path:
        return self.path / layout.STATE_H5

    @property
    def out(self) -> Path:
        return self.path / "out"

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _job_identity(
    operation: str, config: HierarchyConfig, refs: RefTable, **extra: Any
) -> dict[str, Any]:
    """What makes a resumable job the same job (``job.json``): operation, config, inputs."""
    h = _names_digest(refs)
    for k in sorted(refs.meta):
        h.update(k.encode() + np.asarray(refs.meta[k]).astype(str).tobytes())
    return {"operation": operation, "config": config.digest(), "images": h.hexdigest(), **extra}


# -- fitting and extraction ------------------------------------------------------------------
def _readable(
    paths: list[Path], strict: bool
) -> tuple[ImageCheck, list[Path], list[dict[str, str]]]:
    """Every image's sha256 (:attr:`ImageCheck.digests`), the decodable images of ``paths``
    and the skipped ones (name, reason): each file read once, before any work
    (:func:`indexer.inputs.check_images`).

    Raises:
        IndexBuildError: with ``strict``, naming every unreadable image.
    """
    check = check_images(paths)
    bad = check.unreadable
    if bad and strict:
        them = "it" if len(bad) == 1 else f"these {len(bad)}"
        raise IndexBuildError(
            "; ".join(str(exc) for exc in bad.values())
            + f" (rerun without --strict to skip {them})"
        )
    skipped = [{"name": p.name, "reason": exc.reason} for p, exc in bad.items()]
    return check, [p for p in paths if p not in bad], skipped


@contextlib.contextmanager
def _images_stay_readable() -> Iterator[None]:
    """An image that passed :func:`_readable` but fails later: an error naming it, no retry."""
    try:
        yield
    except ImageError as exc:
        raise IndexBuildError(
            f"{exc}, after it passed the check before extraction (was it changed meanwhile?); "
            "rerun, or move it out of the folder"
        ) from None


def _fit(methods: Mapping[str, Method], paths: list[Path], work: WorkDir) -> None:
    """Fit the methods that need it (or reload the state a previous run saved)."""
    todo = {mid: m for mid, m in methods.items() if m.requires_fit()}
    if not todo:
        return
    if work.state.exists():
        states = read_state(work.state)
        for mid, m in todo.items():
            m.load_state(states[mid])
        return
    with _images_stay_readable():
        # with the work cache: the features the fit computes on the way are not extracted again
        hfeatures.fit_methods(todo, paths, cache=work.cache)
    write_state(work.state, todo)


def _extract(
    paths: list[Path], methods: Mapping[str, Method], work: WorkDir, opt: BuildOptions
) -> tuple[dict[str, list[Any]], int]:
    """Features of every image (finished images persist in ``work``).

    Returns:
        features per method id, and how many images were already done.
    """
    if not methods:
        return {}, 0
    resumed: int | None = None
    if opt.ray is not None:
        with _images_stay_readable():  # the features land in the cache, read back below
            resumed = extract_to_cache(paths, methods, work.cache, opt.ray, progress=opt.progress)
    with _images_stay_readable():
        res = extract_images(
            paths,
            methods,
            cache=work.cache,
            workers=opt.workers,
            progress=opt.progress,
            desc="extract",
        )
    return res.features, min(res.cached.values()) if resumed is None else resumed


# -- writing -----------------------------------------------------------------------------------
def _write_faiss(
    out: Path,
    config: HierarchyConfig,
    methods: Mapping[str, Method],
    cols: Mapping[str, Columns],
    opt: BuildOptions,
    parent: IndexReader | None,
    retrain: bool,
) -> dict[str, dict[str, Any] | None]:
    """One FAISS file per tier-1 global method with a FAISS metric (its declaration)."""
    info: dict[str, dict[str, Any] | None] = {}
    for mid in config.tiers[0].methods:
        m = methods[mid]
        if m.kind != "global":
            continue
        factory, params = opt.factory(mid), opt.params(mid)
        col = cols[mid]
        assert isinstance(col, np.ndarray | RowBlocks)
        if isinstance(col, RowBlocks) and int(getattr(m.config, "dba", 0) or 0):
            raise IndexBuildError(
                f"method {mid!r}: dba averages route neighbours over the whole matrix, which "
                "rows given block by block (RowBlocks) do not allow"
            )
        matrix = m.augment_references(col)  # type: ignore[attr-defined]  # dba
        metric = _tier1_metric(mid, m, factory)
        if metric is None:
            info[mid] = None
            continue
        entry: dict[str, Any] = {
            "file": None,
            "factory": factory,
            "params": params,
            "exact": is_exact_factory(factory),
            "metric": metric.to_json(),
            "ntotal": int(matrix.shape[0]),
        }
        if not entry["exact"]:
            # An exact Flat index is the stored matrix itself: the reader builds it in memory
            # instead of keeping a second copy on disk.
            index, metric = _faiss_for(mid, matrix, metric, factory, params, parent, retrain)
            (out / layout.FAISS_DIR).mkdir(exist_ok=True)
            entry["file"] = f"{layout.FAISS_DIR}/{mid}.faiss"
            entry["metric"] = metric.to_json()
            faiss_module().write_index(index, str(out / entry["file"]))
        info[mid] = entry
    return info


def _faiss_for(
    mid: str,
    matrix: np.ndarray,
    metric: MetricSpec,
    factory: str,
    params: str,
    parent: IndexReader | None,
    retrain: bool,
) -> tuple[Any, MetricSpec]:
    """Reuse the parent's trained FAISS index (emptied, refilled) or build a new one."""
    old = parent.faiss_info(mid) if parent is not None and mid in parent.methods else None
    if (
        old is not None
        and not retrain
        and old["factory"] == factory
        and old["metric"]["kind"]
        in (
            metric.kind,
            "l2",
        )
    ):
        index = read_faiss(parent.path / old["file"])  # type: ignore[union-attr]
        if index.d == matrix.shape[1]:
            index.reset()
            _add_rows(index, matrix)
            if params:
                set_search_params(index, params)
            return index, MetricSpec(**old["metric"])
    if isinstance(matrix, RowBlocks):
        return _faiss_from_blocks(matrix, metric, factory, params)
    return build_faiss(matrix, metric, factory, params)


#: Rows an approximate FAISS index of rows given block by block (:class:`RowBlocks`) is
#: trained on: an evenly spaced sample (every row when fewer).
FAISS_TRAIN_ROWS = 65_536


def _faiss_from_blocks(
    rows: RowBlocks, metric: MetricSpec, factory: str, params: str
) -> tuple[Any, MetricSpec]:
    """:func:`~hmpf.index.ann.build_faiss` trained on an evenly spaced sample of
    :data:`FAISS_TRAIN_ROWS` rows, then emptied and filled block by block (a million
    NetVLAD rows are 24 GiB as float32)."""
    n = rows.shape[0]
    pick = np.unique(np.linspace(0, n - 1, min(n, FAISS_TRAIN_ROWS)).round().astype(np.int64))
    index, metric = build_faiss(rows.take(pick), metric, factory, params)
    index.reset()
    _add_rows(index, rows)
    return index, metric


def _add_rows(index: Any, matrix: np.ndarray | RowBlocks) -> None:
    """Add every row of ``matrix`` to a trained FAISS ``index`` (block by block for
    :class:`RowBlocks`)."""
    if isinstance(matrix, RowBlocks):
        for _, block in matrix.blocks():
            index.add(np.ascontiguousarray(block, dtype=np.float32))
    else:
        index.add(np.ascontiguousarray(matrix, dtype=np.float32))


@dataclass
class NewVersion:
    """The contents of a version about to be published, and what made them.

    Attributes:
        config: the hierarchy the methods come from.
        methods: method id -> instance (fitted where needed).
        refs: the references, in row order.
        cols: method id -> its columns (:mod:`hmpf.index.tables`), rows aligned with ``refs``.
        options: how to store them (precision, FAISS factories and parameters).
        parent: the version this one derives from (``add``, ``remove``), else None.
        retrain: train approximate FAISS indexes anew instead of refilling the parent's.
        thumbnails: the references' thumbnails (:mod:`hmpf.index.thumbnails`), rows aligned
            with ``refs``; None: the version stores none (derived from a version without).
        report: what a merge of experiences or their removal did (manifest ``experiences``,
            :class:`Summary` ``experiences``); None for other operations.
        choice: why ``build --config auto`` chose the config (manifest ``choice``); None
            otherwise.
        map_prior: the manifest's ``map_prior`` entry (:func:`map_prior_entry`); None: the
            parent's, if it has one under the same config, else none.
    """

    config: HierarchyConfig
    methods: Mapping[str, Method]
    refs: RefTable
    cols: Mapping[str, Columns]
    options: BuildOptions
    parent: IndexReader | None = None
    retrain: bool = True
    thumbnails: Ragged | None = None
    report: dict[str, Any] | None = None
    choice: dict[str, Any] | None = None
    map_prior: dict[str, Any] | None = None


class VersionTransaction:
    """Writing one new version of the index at ``root``, from start to atomic publish.

    ::

        tx = VersionTransaction(root, "build")     # the clock starts (Summary.seconds)
        with tx:                                   # the index's writer lock
            tx.begin(job, resume)                  # INDEX/.build (job.json, features/)
            ...                                    # fit and extract into tx.work
            summary = tx.publish(NewVersion(...), extracted=n)

    An exception before :meth:`publish` returns leaves ``CURRENT`` and every published
    version untouched, and ``.build`` in place for ``--resume``.
    """

    def __init__(self, root: Path, operation: str) -> None:
        self.root = root
        self.operation = operation
        self.work = WorkDir(root)
        self._started = time.perf_counter()
        self._lock = contextlib.ExitStack()

    def __enter__(self) -> VersionTransaction:
        self._lock.enter_context(layout.writer_lock(self.root))
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.close()

    def restart_clock(self) -> None:
        """Time the operation from now on (what came before is timed on its own)."""
        self._started = time.perf_counter()

    def begin(self, job: dict[str, Any], resume: bool = False) -> bool:
        """Create the work folder for ``job`` (see :meth:`WorkDir.start`)."""
        return self.work.start(job, resume)

    def publish(
        self,
        new: NewVersion,
        *,
        extracted: int,
        resumed: int = 0,
        skipped: Sequence[dict[str, str]] = (),
    ) -> Summary:
        """Write ``new`` into ``.build/out``, fsync it, rename it to the next version name,
        stamp it as verified (its sha256 were computed from its files:
        :func:`hmpf.index.layout.write_stamp`), switch ``CURRENT`` to it and delete ``.build``.

        Args:
            extracted: references whose features this operation computed (the rest reused).
            resumed: of those, how many a previous, interrupted run had finished.
            skipped: unreadable images left out, ``{"name", "reason"}`` each.
        """
        if len(new.refs) == 0:
            raise IndexBuildError("no readable reference image left; nothing to index")
        check_places(new.refs)
        out = self.work.out
        if out.exists():
            shutil.rmtree(out)  # a partial write of an interrupted run: features are cached
        out.mkdir()
        name = layout.next_version_name(self.root)
        try:
            sizes, faiss_info, profile = _write_data(out, new)
            models = write_models(out, new.methods)  # the CNN models queries run (ONNX)
            thumb_bytes = 0
            if new.thumbnails is not None:
                thumb_bytes = thumbnails.write_thumbnails(out / thumbnails.FILE, new.thumbnails)
            seconds = time.perf_counter() - self._started
            summary = Summary(
                version=name,
                operation=self.operation,
                images=len(new.refs),
                extracted=extracted,
                reused=len(new.refs) - extracted,
                skipped=list(skipped),
                resumed=resumed,
                seconds=seconds,
                images_per_s=(extracted or len(new.refs)) / max(seconds, 1e-9),
                bytes_total=0,
                bytes_per_method=sizes,
                bytes_thumbnails=thumb_bytes,
            )
            summary.experiences = new.report
            summary.choice = _choice_summary(new.choice)
            manifest = _manifest(name, self.operation, new, faiss_info, models)
            summary.map_prior_note = prior_note(new.config, manifest.get("map_prior"))
            manifest["profile"] = profile
            manifest["summary"] = asdict(summary)
            stats = layout.file_stats(out)  # before hashing: the stamp vouches for these
            manifest["files"] = _file_entries(out)
            summary.bytes_total = sum(f["bytes"] for f in manifest["files"].values())
            summary.bytes_models = sum(
                f["bytes"]
                for path, f in manifest["files"].items()
                if path.startswith(f"{MODELS_DIR}/")
            )
            manifest["summary"]["bytes_total"] = summary.bytes_total
            manifest["summary"]["bytes_models"] = summary.bytes_models
            sealed = layout.write_manifest(out, manifest)
            layout.fsync_tree(out)
            out.rename(self.root / name)
            layout.fsync_dir(self.root)
            # Every sha256 was just computed from these files: stamp them as checked in full
            # (a reader opening them by stamp hashes nothing), before CURRENT names them.
            layout.write_stamp(self.root / name, sealed, stats)
            layout.set_current(self.root, name)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                raise IndexBuildError(
                    f"disk full while writing {out}; free space, then rerun with --resume "
                    "(finished images are kept; the current version is untouched)"
                ) from None
            raise
        self.work.discard()
        return summary


def _write_data(
    out: Path, new: NewVersion
) -> tuple[dict[str, int], dict[str, dict[str, Any] | None], dict[str, Any]]:
    """The HDF5 and FAISS files of ``new`` and its places' reference profile; returns bytes
    per method, the FAISS entries and the manifest's ``profile`` entry."""
    opt = new.options
    glob = {m: c for m, c in new.cols.items() if isinstance(c, np.ndarray | RowBlocks)}
    loc = {m: c for m, c in new.cols.items() if isinstance(c, dict)}
    sizes = write_references(out / layout.REFERENCES_H5, new.refs, glob, new.methods, opt.precision)
    if loc:
        sizes.update(write_local(out / layout.LOCAL_H5, loc, new.methods, opt.precision))
    if any(m.state_arrays() for m in new.methods.values()):
        write_state(out / layout.STATE_H5, new.methods)
    faiss_info = _write_faiss(out, new.config, new.methods, new.cols, opt, new.parent, new.retrain)
    for mid, fi in faiss_info.items():
        if fi is not None and fi["file"]:
            sizes[mid] += (out / fi["file"]).stat().st_size
    return sizes, faiss_info, _write_profile(out, new.config, new.methods)


def _write_profile(
    out: Path, config: HierarchyConfig, methods: Mapping[str, Method]
) -> dict[str, Any]:
    """Write ``profile.h5``: the places' :class:`~hmpf.confidence.ReferenceProfile` of the
    version being written in ``out``, computed as a reader of the version would compute it at
    load (:func:`~hmpf.index.places.places_profile` over the descriptors and metadata read
    back from its ``references.h5``, so stored precision included), so that no reader has to.

    Returns:
        the manifest's ``profile`` entry: the file, the profiled methods, the parameters
        (:func:`~hmpf.confidence.profile_params`) and the seconds it took.
    """
    started = time.perf_counter()
    tier1 = [m for m in config.tiers[0].methods if methods[m].kind == "global"]
    with open_h5(out / layout.REFERENCES_H5) as f:
        refs = read_ref_table(f)
        where = str(out / layout.REFERENCES_H5)
        places = Places.from_column(refs.meta.get("place"), len(refs), where)
        P = places.n
        searched: dict[str, Any] = {}
        for m in tier1:
            # Without dba, the places' rows as a reader reads them on demand (a million
            # NetVLAD rows do not fit in memory as float32); the profile reads them in chunks.
            rows = None if augments(methods[m]) else disk_rows(f["global"][m])
            if rows is not None:
                searched[m] = rows.head(P)
                rows.close()
                continue
            # The places' rows are augmented among themselves whatever follows them
            # (augment_rows' first P rows), so the experience rows need not be.
            stored = read_global(f, m)[:P]
            searched[m] = augment_rows(methods[m], stored, Places.identity(P))
        profile = places_profile(config, methods, searched, route_map_of(refs.meta, P, config))
        for rows in searched.values():
            if isinstance(rows, DiskRows):
                rows.close()
    params = profile_params()
    write_profile(out / layout.PROFILE_H5, profile, params)
    return {
        "file": layout.PROFILE_H5,
        "methods": list(profile.methods),
        "params": params,
        "seconds": round(time.perf_counter() - started, 3),
    }


# -- the manifest ------------------------------------------------------------------------------
def _names_digest(refs: RefTable) -> hashlib._Hash:
    """sha256 over every reference's ``name<TAB>sha256`` line, in order (to be finished)."""
    h = hashlib.sha256()
    for n, s in zip(refs.names, refs.sha256, strict=True):
        h.update(f"{n}\t{s}\n".encode())
    return h


def _manifest(
    name: str,
    operation: str,
    new: NewVersion,
    faiss_info: Mapping[str, dict[str, Any] | None],
    models: Sequence[dict[str, Any]] = (),
) -> dict[str, Any]:
    """``manifest.json`` of version ``name`` without ``summary`` and ``files`` (added last);
    ``models``: the exported CNN models stored (:func:`hmpf.index.models.write_models`)."""
    refs, config = new.refs, new.config
    sources = sorted(set(refs.sources))
    out: dict[str, Any] = {
        "format_version": layout.FORMAT_VERSION,
        "version": name,
        "parent": new.parent.version if new.parent is not None else None,
        "operation": operation,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "config": {"name": config.name, "sha256": config.digest(), "resolved": config.model_dump()},
        "methods": {
            mid: _method_entry(m, new.cols[mid], faiss_info.get(mid))
            for mid, m in new.methods.items()
        },
        "packages": layout.package_versions(),
        "models": list(models),
        "platform": {"machine": platform.machine(), "system": platform.system(), "argv": sys.argv},
        "options": new.options.identity(),
        "images": {
            "count": len(refs),
            "list_sha256": _names_digest(refs).hexdigest(),
            "table": f"{layout.REFERENCES_H5}:/names,/sha256",
            "sources": [{"folder": s, "count": refs.sources.count(s)} for s in sources],
            "metadata_columns": sorted(refs.meta),
        },
        "thumbnails": None
        if new.thumbnails is None
        else {
            "file": thumbnails.FILE,
            "max_side": thumbnails.MAX_SIDE,
            "quality": thumbnails.QUALITY,
        },
    }
    places = _places_entry(refs)
    if places is not None:
        out["places"] = places
    if new.report is not None:
        out["experiences"] = new.report
    if new.choice is not None:
        out["choice"] = new.choice
    prior = new.map_prior if new.map_prior is not None else _carried_prior(new)
    if prior is not None:
        out["map_prior"] = prior
    return out


def prior_note(config: HierarchyConfig, entry: Mapping[str, Any] | None) -> str | None:
    """The build's warning when ``config``'s acceptance models (its own or the shipped ones)
    read the map's prior and the version's manifest entry ``entry`` holds none."""
    acc = with_shipped_acceptance(config).acceptance
    if acc is None or not acc.reads_map_prior or (entry or {}).get("map_prior") is not None:
        return None
    if acc.map_prior_fallback is None:
        then = "hmpf-serve will refuse it"
    else:
        then = (
            f"hmpf-serve uses the models' conservative fallback {acc.map_prior_fallback:+.2f}, "
            "so fewer answers will be accepted"
        )
    why = (entry or {}).get("why_none")
    fix = f"none could be computed ({why})" if why else "build with --map-prior"
    return f"no map prior stored, which this config's acceptance models read: {then}; {fix}"


def map_prior_entry(
    config: HierarchyConfig,
    paths: Sequence[Path],
    refs: RefTable,
    cache: FeatureCache | None,
    options: BuildOptions,
) -> dict[str, Any]:
    """The manifest's ``map_prior`` entry: the config's recall@1 on pseudo-queries of the
    references ``paths`` (``refs``' rows, their metadata giving the route order;
    :func:`hmpf.evaluation.auto.map_prior`), under the config's digest. Too few references
    to make pseudo-queries from: the entry says why, with no value."""
    meta: dict[str, Any] = {
        k: refs.meta[k] for k in ("sequence", "timestamp", "lat", "lon") if k in refs.meta
    }
    found = map_prior_or_why(
        config,
        list(paths),
        metadata=meta,
        cache=cache,
        workers=options.workers,
        progress=options.progress,
    )
    return {"config_sha256": config.digest(), **found}


def _carried_prior(new: NewVersion) -> dict[str, Any] | None:
    """The parent's ``map_prior`` entry for a version derived from it under the same config
    (``add``, ``remove``, experiences), marked with the version it was computed in; None
    without one."""
    if new.parent is None:
        return None
    entry = new.parent.manifest.get("map_prior")
    if not isinstance(entry, dict) or entry.get("config_sha256") != new.config.digest():
        return None
    return {**entry, "computed_in": entry.get("computed_in", new.parent.version)}


def _choice_summary(choice: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """What :class:`Summary` keeps of an automatic choice's record (the manifest has it all)."""
    if choice is None:
        return None
    return {k: choice[k] for k in ("seed", "chosen", "digest", "time_s")}


def _method_entry(
    m: Method, cols: Columns | RowBlocks, faiss: dict[str, Any] | None
) -> dict[str, Any]:
    """A method's manifest entry: type, version, parameters, state hash, FAISS, shapes."""
    entry: dict[str, Any] = {
        "type": type(m).name,
        "kind": m.kind,
        "version": type(m).version,
        "params": m.config.model_dump(mode="json"),
        "cache_key": m.cache_key(),
        "higher_is_better": m.higher_is_better,
        "state_sha256": m.state_digest(),
        "faiss": faiss,
    }
    if isinstance(cols, np.ndarray | RowBlocks):
        entry["dim"] = int(cols.shape[1])
        entry["dtype"] = cols.dtype.str
    else:
        entry["arrays"] = {k: _array_entry(r) for k, r in cols.items()}
    return entry


def _array_entry(r: Ragged | RowBlocks) -> dict[str, Any]:
    """A local array's dtype and per-row shape (:class:`RowBlocks` ``(N, n, ...)``: the
    rows of its ``n``-row items)."""
    if isinstance(r, RowBlocks):
        return {"dtype": r.dtype.str, "item_shape": list(r.shape[2:])}
    return {"dtype": r.data.dtype.str, "item_shape": list(r.data.shape[1:])}


def _file_entries(out: Path) -> dict[str, dict[str, Any]]:
    """``files`` of the manifest: every file under ``out`` -> its size and sha256 (and its
    pieces' sha256 when large, :func:`hmpf.index.layout.file_entry`)."""
    return {
        str(p.relative_to(out)): layout.file_entry(p) for p in sorted(out.rglob("*")) if p.is_file()
    }


# -- operations --------------------------------------------------------------------------------
def build(
    config: str | Path | HierarchyConfig,
    images: str | Path,
    index: str | Path,
    *,
    metadata: str | Path | None = None,
    options: BuildOptions | None = None,
    resume: bool = False,
    seed: int = 0,
    cache: FeatureCache | None = None,
    auto_options: Mapping[str, Any] | None = None,
    with_map_prior: bool | None = None,
) -> Summary:
    """Extract every method for every image of ``images`` and publish a new version.

    ``with_map_prior``: also store the config's recall@1 on pseudo-queries of the
    references (:func:`map_prior_entry`; the manifest's ``map_prior``, carried to the
    versions derived from this one), through ``cache`` when given; None (the default): when
    the config's acceptance models (its own or the shipped ones) read it.

    ``config`` ``"auto"`` (:data:`AUTO`) chooses the hierarchy and its acceptance models from
    the readable references and ``metadata`` alone, on pseudo-queries made from them
    (:func:`hmpf.evaluation.auto.choose_config`; deterministic for ``seed``; ``cache``: the
    feature cache the choice reads and fills, so a rerun or ``resume`` does not extract the
    sample again; ``auto_options``: more of its options, e.g. ``pool`` or ``budget_ms``),
    under the writer lock and before any reference is extracted; the manifest's ``choice``
    records why (candidates, their pseudo-query recall, the held-out test, the seed, the
    sample, the time).

    Raises:
        ConfigError, DatasetError, IndexBuildError: bad input, before any extraction.
    """
    tx = VersionTransaction(Path(index), "build")
    automatic = isinstance(config, str) and config == AUTO
    base = options or BuildOptions()
    if not automatic:
        cfg = _load_config(config)
        opt = base.with_config(cfg)
        methods = build_methods(cfg)
        _check_options(cfg, methods, opt)
    paths, refs = _read_inputs(images, metadata)
    choice: dict[str, Any] | None = None
    with tx:
        check, paths, skipped = _readable(paths, base.strict)
        refs.sha256 = check.digests
        if automatic:
            cfg, choice = _choose(paths, refs, seed, cache, base, auto_options or {})
            tx.restart_clock()  # the summary times the build; the choice says its own time
            opt = base.with_config(cfg)
            methods = build_methods(cfg)
            _check_options(cfg, methods, opt)
        tx.begin(_job_identity("build", cfg, refs, options=opt.identity()), resume)
        _fit(methods, paths, tx.work)
        feats, resumed = _extract(paths, methods, tx.work, opt)
        refs = refs.select(_kept(refs, paths))
        cols = {mid: columns_from_features(m, feats[mid]) for mid, m in methods.items()}
        thumbs = _thumbnails(paths, refs, tx.work)
        if with_map_prior is None:
            acc = with_shipped_acceptance(cfg).acceptance
            with_map_prior = acc is not None and acc.reads_map_prior
        prior = map_prior_entry(cfg, paths, refs, cache, opt) if with_map_prior else None
        new = NewVersion(
            cfg, methods, refs, cols, opt, thumbnails=thumbs, choice=choice, map_prior=prior
        )
        return tx.publish(new, extracted=len(refs), resumed=resumed, skipped=skipped)


def _choose(
    paths: Sequence[Path],
    refs: RefTable,
    seed: int,
    cache: FeatureCache | None,
    options: BuildOptions,
    auto_options: Mapping[str, Any],
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """``--config auto``: the hierarchy and its acceptance chosen from the readable
    references ``paths`` and their metadata alone (:func:`hmpf.evaluation.auto.choose_config`),
    and the record of why (stored in the version's manifest as ``choice``)."""
    kept = _kept(refs, paths)
    meta = {k: np.asarray(v)[kept] for k, v in refs.meta.items()}
    cfg, reasons = choose_config(
        list(paths),
        meta,
        seed=seed,
        cache=cache,
        **{"workers": options.workers, "progress": options.progress, **auto_options},
    )
    return cfg, reasons


def _thumbnails(paths: Sequence[Path], refs: RefTable, work: WorkDir) -> Ragged:
    """Thumbnails of ``paths`` (``refs``' rows), kept in the work folder for ``--resume``."""
    with _images_stay_readable():
        return thumbnails.make_thumbnails(paths, refs.sha256, work.path / "thumbnails")


def _kept(refs: RefTable, paths: Sequence[Path]) -> np.ndarray:
    pos = {n: i for i, n in enumerate(refs.names)}
    return np.array([pos[p.name] for p in paths], dtype=np.int64)


def _row_thumbnails(parent: IndexReader) -> Ragged:
    """Every stored row's thumbnail (empty entries in a version without thumbnails)."""
    if parent.thumbnails is None:
        return empty_thumbnails(len(parent.refs))
    return parent.thumbnail_column()


# -- places and experiences ------------------------------------------------------------------
def place_count(refs: RefTable) -> int:
    """P, the number of places: the rows before the first experience row (every row in a
    version without experiences). Computed from the ``place`` column, not from a reader's
    count, so that it means the same whatever the reader counts."""
    place = refs.meta.get("place")
    if place is None:
        return len(refs)
    exp = ~np.isnan(np.asarray(place, dtype=np.float64))
    return int(np.argmax(exp)) if exp.any() else len(refs)


def check_places(refs: RefTable) -> int:
    """P, after checking the rows keep the format's order: every original reference (``place``
    NaN) before every experience, and each experience naming one of those places.

    Raises:
        IndexBuildError: the rows break it (a bug: the version is not written).
    """
    n_places = place_count(refs)
    place = refs.meta.get("place")
    if place is None:
        return n_places
    exp = np.asarray(place, dtype=np.float64)[n_places:]
    if not ((exp >= 0) & (exp < n_places) & (exp == np.floor(exp))).all():
        raise IndexBuildError(
            f"refusing to write a version whose experience rows do not all follow the {n_places} "
            "places they name (an internal error; the current version is untouched)"
        )
    return n_places


def without_empty_experiences(refs: RefTable) -> RefTable:
    """``refs`` without the experience columns when no experience row is left (the version
    is then stored as one that never had any)."""
    if place_count(refs) < len(refs):
        return refs
    meta = {k: v for k, v in refs.meta.items() if k not in EXPERIENCE_COLUMNS}
    return RefTable(refs.names, refs.sha256, meta, refs.sources)


def _places_entry(refs: RefTable) -> dict[str, int] | None:
    """The manifest's ``places`` entry: P and N - P, only where some row is an experience."""
    n_places = place_count(refs)
    if n_places == len(refs):
        return None
    return {"count": n_places, "experiences": len(refs) - n_places}


def _parent_options(parent: IndexReader, options: BuildOptions | None) -> BuildOptions:
    """Storage options for a version derived from ``parent``: the parent's own (FAISS
    factories and parameters, precision), those ``options`` name over them."""
    stored = parent.manifest.get("options", {})
    base = BuildOptions(
        faiss=dict(stored.get("faiss", {})),
        faiss_params=dict(stored.get("faiss_params", {})),
        precision=stored.get("precision", "exact"),
        strict=bool(stored.get("strict", False)),
        progress=False,
    )
    if options is None:
        return base
    return replace(
        options,
        faiss={**base.faiss, **options.faiss},
        faiss_params={**base.faiss_params, **options.faiss_params},
        precision=base.precision,
    )


def _parent(root: Path, operation: str) -> IndexReader:
    """The current version, every file verified against its sha256 first: a derived version
    copies its rows, and its manifest would vouch for them.

    Raises:
        IndexCorruptError: the current version does not verify (nothing is written).
    """
    try:
        return IndexReader(root, verify=True)
    except IndexCorruptError as exc:
        raise IndexCorruptError(
            f"{operation} refused, it would copy corrupt data into a new version: {exc}"
        ) from None


def add(
    index: str | Path,
    images: str | Path,
    *,
    metadata: str | Path | None = None,
    options: BuildOptions | None = None,
    refit: bool = False,
    resume: bool = False,
) -> Summary:
    """Publish a version with the images of ``images`` as new places of the current version.

    Stored features of the current references are reused. With ``refit``, methods with
    fitted parameters are refitted on old + new images, which then must still be readable
    where they were indexed from (unchanged), and those methods are re-extracted for all.
    In a version with experiences the new places go after the places and before the
    experience rows (each experience keeps its place's index); ``refit`` is refused there.
    """
    tx = VersionTransaction(Path(index), "add")
    paths, new = _read_inputs(images, metadata)
    with tx, _parent(tx.root, "add") as parent:
        opt = (options or BuildOptions()).with_config(parent.config)
        _check_options(parent.config, parent.methods, opt)
        n_places = place_count(parent.refs)
        if refit and n_places < len(parent.refs):
            raise IndexBuildError(
                f"--refit re-extracts every reference from its image file, but {parent.version} "
                f"holds {len(parent.refs) - n_places} fleet experience(s), whose frames are not "
                "kept as files; add without --refit, or build anew from the reference images "
                "and merge the experience logs again"
            )
        clash = sorted(set(new.names) & set(parent.refs.names))
        if clash:
            raise IndexBuildError(
                f"{len(clash)} image(s) already in the index: {', '.join(clash[:5])}; "
                "remove them first (hmpf-index remove) or rename them"
            )
        check, paths, skipped = _readable(paths, opt.strict)
        new.sha256 = check.digests
        job = _job_identity(
            "add", parent.config, new, parent=parent.version, refit=refit, options=opt.identity()
        )
        tx.begin(job, resume)
        methods = parent.methods
        refit_ids: list[str] = []
        if refit:
            methods, refit_ids = _refit(parent, paths, tx.work)
        reuse = {mid: m for mid, m in methods.items() if mid not in refit_ids}
        feats, resumed = _extract(paths, reuse, tx.work, opt)
        new = new.select(_kept(new, paths))
        cols = {
            mid: concat_columns(parent.columns(mid), columns_from_features(m, feats[mid]))
            for mid, m in reuse.items()
        }
        refs = parent.refs.concat(new)
        # new places before the experience rows: rows 0 .. P-1 stay the places, in order
        order = _insert_order(n_places, len(parent.refs), len(new))
        refs = refs.select(order)
        cols = {mid: select_columns(c, order) for mid, c in cols.items()}
        if refit_ids:
            all_paths = [Path(s) / n for s, n in zip(refs.sources, refs.names, strict=True)]
            fresh = {mid: methods[mid] for mid in refit_ids}
            feats_all, _ = _extract(all_paths, fresh, tx.work, opt)
            cols.update({mid: columns_from_features(fresh[mid], feats_all[mid]) for mid in fresh})
        thumbs = Ragged.concat([_row_thumbnails(parent), _thumbnails(paths, new, tx.work)])
        thumbs = thumbs.select(order)
        version = NewVersion(
            parent.config, methods, refs, cols, opt, parent, retrain=refit, thumbnails=thumbs
        )
        return tx.publish(version, extracted=len(new), resumed=resumed, skipped=skipped)


def _insert_order(n_places: int, n_rows: int, n_new: int) -> np.ndarray:
    """Row order of ``parent rows + new rows`` with the new rows moved before the parent's
    experience rows (rows ``n_places ..``)."""
    return np.concatenate(
        [
            np.arange(n_places),
            np.arange(n_rows, n_rows + n_new),
            np.arange(n_places, n_rows),
        ]
    ).astype(np.int64)


def _refit(
    parent: IndexReader, new_paths: list[Path], work: WorkDir
) -> tuple[dict[str, Method], list[str]]:
    """Refit fitted methods on the old (from their folders, unchanged) and new images."""
    methods = build_methods(parent.config)
    if not any(m.requires_fit() for m in methods.values()):
        return parent.methods, []
    old_paths = [Path(s) / n for s, n in zip(parent.refs.sources, parent.refs.names, strict=True)]
    for p, sha in zip(old_paths, parent.refs.sha256, strict=True):
        if not p.exists() or file_digest(p) != sha:
            raise IndexBuildError(
                f"--refit re-extracts every reference, but {p} is missing or changed since "
                "it was indexed; restore it, or add without --refit"
            )
    _fit(methods, old_paths + new_paths, work)
    ids = [
        mid for mid, m in methods.items() if m.state_digest() != parent.methods[mid].state_digest()
    ]
    for mid, m in parent.methods.items():
        if mid not in ids:
            methods[mid] = m
    return methods, ids


def remove(
    index: str | Path, names: Sequence[str], *, options: BuildOptions | None = None
) -> Summary:
    """Publish a version of the current one without the references ``names``.

    Removing a place's original reference removes the place with its experiences, and the
    later places are renumbered (their experiences follow); an experience row may also be
    removed by its name. The version keeps the parent's storage options.
    """
    tx = VersionTransaction(Path(index), "remove")
    with tx, _parent(tx.root, "remove") as parent:
        present = set(parent.refs.names)
        missing = [n for n in names if n not in present]
        if missing:
            raise IndexBuildError(
                f"not in {parent.version}: {', '.join(missing[:5])}"
                + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
                + "; see `hmpf-index info --names`"
            )
        keep, refs = _without_rows(parent.refs, set(names))
        if place_count(refs) == 0:
            raise IndexBuildError("removing every reference would leave an empty index")
        cols = {mid: select_columns(parent.columns(mid), keep) for mid in parent.methods}
        tx.begin({"operation": "remove", "parent": parent.version, "names": sorted(set(names))})
        new = NewVersion(
            parent.config,
            parent.methods,
            refs,
            cols,
            _parent_options(parent, options),
            parent,
            retrain=False,
            thumbnails=None if parent.thumbnails is None else _row_thumbnails(parent).select(keep),
        )
        return tx.publish(new, extracted=0)


def _without_rows(refs: RefTable, drop: set[str]) -> tuple[np.ndarray, RefTable]:
    """The rows kept when the rows named ``drop`` go, and the table of them: a dropped place
    takes its experiences along, the places left are renumbered in order (the experiences'
    ``place`` follows), and the experience columns go when no experience is left."""
    n_places = place_count(refs)
    names = refs.names
    gone = np.array([n in drop for n in names], dtype=bool)
    place = refs.meta.get("place")
    if place is None:
        keep = np.flatnonzero(~gone).astype(np.int64)
        return keep, refs.select(keep)
    place_of = np.concatenate([np.arange(n_places), place[n_places:]]).astype(np.int64)
    gone |= gone[:n_places][place_of]  # a removed place's experiences go with it
    keep = np.flatnonzero(~gone).astype(np.int64)
    renumber = np.cumsum(~gone[:n_places]) - 1  # old place -> new place (kept ones)
    out = refs.select(keep)
    new_place = np.full(len(keep), np.nan)
    exp = keep >= n_places
    new_place[exp] = renumber[place_of[keep[exp]]]
    out.meta["place"] = new_place
    return keep, without_empty_experiences(out)
