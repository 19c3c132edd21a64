"""Read-only access to one index version, and hierarchy scoring over it.

The service and ``hmpf-eval --index`` both go through :class:`IndexReader`::

    reader = IndexReader("maps/campus")            # the version CURRENT names
    hier = reader.hierarchy()
    query = reader.extract_query(image)            # method id -> feature
    result = hier.run(reader.scorer(query), reader.n)
    reader.refs.names[result.match]                # the place (its original reference)

Places and experiences (:mod:`hmpf.index.places`): a version's rows are its places' original
references first (row ``p`` is place ``p``), then fleet experiences of those places.
:attr:`IndexReader.n` counts places, :attr:`IndexReader.n_rows` rows. The hierarchy, route
maps, the reference profile and answers run over places; the stored arrays (features,
thumbnails, FAISS) over rows. In a version with experiences :meth:`IndexReader.scorer` is
place-level (a place scores by its best experience, per method, before normalisation) and
:meth:`IndexReader.matched_rows` says which experience matched each place; a version without
experiences scores exactly as before (the row scorer itself).

Tier 1 (``subset is None``) of a global method (over rows; then reduced per place):

* exact FAISS type (``Flat``, the default): the method scores the stored (memory-mapped)
  matrix directly, so results are bit-identical to in-memory evaluation (``hmpf-eval``
  without ``--index``); the FAISS file serves :meth:`IndexReader.search`.
* approximate type (IVF / HNSW / PQ): FAISS returns the top ``approx_k`` candidates
  (default ``max(256, 4 k)`` for the tier's k); they and a fixed, evenly spaced sample of up
  to 1024 references are scored exactly by the method; every other reference gets the worst
  of those exact scores. Min-max normalisation over the database then uses the exact best (if
  FAISS found it) and a worst value estimated from the sample, and references outside the
  candidates normalise to 0, which is what they would score in the later fusion anyway
  unless they were among the top k.

Later tiers read only the candidates' rows: global rows from the matrix, local features
(KAZE ragged rows, OLO blocks) from ``local.h5`` by offsets, decoded ones kept in a cache
bounded in bytes (``local_cache_bytes``).

What stays in memory (:meth:`IndexReader.on_demand`): the matrix of a global method that
scores the whole database exactly (tier 1 on an exact FAISS type) or is augmented along
the route (``dba``). Every other global method's rows are read from ``references.h5`` when a
query needs them (:class:`~hmpf.index.rows.DiskRows`: the FAISS candidates of an
approximate tier 1, a later tier's candidates), and of an approximate tier-1 method only
its FAISS index and the fixed sample's rows are resident. So a map on an approximate tier 1
holds a few hundred bytes per reference in memory (the FAISS codes, the reference table)
whatever its descriptors' size; :attr:`IndexReader.read_stats` counts what was read.

Opening a version first checks every one of its files against the size and sha256 in the
manifest (:func:`hmpf.index.layout.check_files`): a damaged byte anywhere, even inside a
dataset where HDF5 cannot see it, is an :class:`IndexCorruptError` naming the file. With
``verify="stamp"`` a version whose files are unchanged since their last full check (its
verification stamp, :func:`hmpf.index.layout.stamp_matches`) opens without hashing them, and
the caller checks them in full afterwards (the service, in the background).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Collection, Mapping
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.confidence import ReferenceProfile, stored_map_prior
from hmpf.config import HierarchyConfig, build_methods, parse_config, with_shipped_acceptance
from hmpf.errors import ConfigError
from hmpf.features import extract_query
from hmpf.fusion import Filled
from hmpf.hierarchy import Hierarchy, ScoreFn
from hmpf.index import layout
from hmpf.index.ann import (
    MetricSpec,
    faiss_module,
    read_faiss,
    search_faiss,
    set_search_params,
    to_raw,
)
from hmpf.index.layout import (
    IndexBuildError,
    IndexCorruptError,
    IndexNotFoundError,
    IndexVersionError,
)
from hmpf.index.models import attach_models, torch_needed
from hmpf.index.places import (
    Experience,
    Places,
    PlaceScorer,
    augment_rows,
    augments,
    experience_of_row,
    experience_sets,
    pair_sample,
    place_scorer,
    places_profile,
    route_map_of,
)
from hmpf.index.rows import DiskRows, LruCache, ReadStats, disk_rows
from hmpf.index.storage import (
    open_h5,
    read_global,
    read_local_columns,
    read_local_items,
    read_local_offsets,
    read_ref_table,
    read_state,
    stored_profile,
)
from hmpf.index.tables import Columns, Ragged
from hmpf.index.thumbnails import ThumbnailStore, empty_thumbnails
from hmpf.methods import Method
from hmpf.sequence import MotionSketch, RouteMap, sketch_method

__all__ = ["IndexReader", "check_packages", "resolve_version"]

SAMPLE_SIZE = 1024
#: default bound of the decoded local features a reader keeps (bytes)
LOCAL_CACHE_BYTES = 64 << 20
log = logging.getLogger("hmpf.index")

#: Packages whose major version changes what the methods compute (OpenCV: HOG, KAZE, image
#: ops; torch: the CNN methods) or how the index files are read (FAISS): a different major
#: version than the build's is an error. Other differences (minor versions, numpy, h5py,
#: onnxruntime) are logged as warnings. torch counts only where a query runs a forward pass
#: in it: a version whose CNN methods run their stored ONNX models (:mod:`hmpf.index.models`,
#: the default runtime) does not depend on torch, which need not even be installed.
STRICT_PACKAGES = (*layout.OPENCV_DISTS, "torch", "faiss-cpu")


def _nbytes(feature: Any) -> int:
    """Memory a decoded feature holds in its arrays (an array, or an object / tuple of
    them), for the local-feature cache's bound."""
    if isinstance(feature, np.ndarray):
        return int(feature.nbytes)
    if dataclasses.is_dataclass(feature):
        parts: Any = [getattr(feature, f.name) for f in dataclasses.fields(feature)]
    else:
        parts = feature if isinstance(feature, tuple) else getattr(feature, "__dict__", {}).values()
    return sum(int(v.nbytes) for v in parts if isinstance(v, np.ndarray)) or 64


def resolve_version(root: Path, version: str | None = None) -> Path:
    """Folder of ``version`` (default: the one ``CURRENT`` names)."""
    if not root.is_dir():
        raise IndexNotFoundError(f"index folder {str(root)!r} does not exist")
    name = version or layout.current_version(root)
    if name is None:
        raise IndexNotFoundError(
            f"{root}: no published index version; build one with `hmpf-index build`"
        )
    path = root / name
    if not path.is_dir():
        raise IndexNotFoundError(
            f"{root}: no version {name!r} (have: {', '.join(layout.list_versions(root)) or 'none'})"
        )
    return path


def _major(version: str) -> str:
    return version.split(".")[0]


def check_packages(
    built_with: Mapping[str, str], where: Path, unused: Collection[str] = ()
) -> list[str]:
    """Compare the build's package versions (manifest ``packages``) with the installed ones.

    ``unused``: packages the reader does not run (torch, when every CNN forward pass runs a
    stored ONNX model), not compared.

    Returns:
        the differences that were only logged as warnings.

    Raises:
        IndexVersionError: a package of :data:`STRICT_PACKAGES` has another major version
            here than at build time (descriptors of new queries would not be comparable with
            the stored ones, or the FAISS files may not load).
    """
    notes: list[str] = []
    for dist, built in sorted(built_with.items()):
        if dist in ("python", "hmpf") or dist in unused or not isinstance(built, str):
            continue
        here = layout.installed_version(dist)
        if here is None and dist.startswith("opencv"):  # the other OpenCV wheel is fine
            here = next(filter(None, map(layout.installed_version, layout.OPENCV_DISTS)), None)
        if here == built:
            continue
        if here is not None and dist in STRICT_PACKAGES and _major(here) != _major(built):
            raise IndexVersionError(
                f"{where}: built with {dist} {built}, this environment has {here}; install "
                f"{dist}=={built} or rebuild the index with `hmpf-index build`"
            )
        notes.append(f"{dist} {built} at build time, {here or 'not installed'} here")
    if notes:
        log.warning("%s: package versions differ from the build: %s", where, "; ".join(notes))
    return notes


class IndexReader:
    """One index version, opened read-only.

    Args:
        root: the index folder.
        version: version name (default: ``CURRENT``).
        expected_config: when given, the index must have been built for exactly this
            hierarchy config (same digest), else :class:`IndexVersionError`.
        mmap: memory-map global matrices stored in their own dtype, and the codes of
            flat-codes FAISS types (:func:`~hmpf.index.ann.read_faiss`) (else read into RAM).
        verify: what is checked before anything is read
            (:func:`~hmpf.index.layout.verify_files`): ``True`` / ``"full"``, every file
            against the manifest's sha256 (the whole version is read once); ``"stamp"``,
            nothing more when the version's verification stamp matches (a ``stat`` per file;
            :attr:`verified_by` then says ``"stamp"`` and the caller owes the full check,
            as the service runs it in the background), else every file, then a fresh stamp;
            ``False``, nothing (only ``hmpf-index verify``, which has just checked them).
        approx_k: FAISS candidates per approximate tier-1 search (default ``max(256, 4 k)``).

    Raises:
        IndexNotFoundError, IndexVersionError, IndexCorruptError: with what to do.
    """

    def __init__(
        self,
        root: str | Path,
        version: str | None = None,
        *,
        expected_config: HierarchyConfig | None = None,
        mmap: bool = True,
        verify: layout.VerifyMode = True,
        approx_k: int | None = None,
        local_cache_bytes: int = LOCAL_CACHE_BYTES,
    ) -> None:
        self.root = Path(root)
        self._mmap = mmap
        self.path = resolve_version(self.root, version)
        self.version = self.path.name
        self.manifest = layout.read_manifest(self.path)
        #: how the files were verified before reading: "full" (every sha256), "stamp" (the
        #: verification stamp matched, nothing hashed) or None (``verify=False``); and the
        #: seconds spent hashing them (None: nothing hashed)
        self.verified_by, self.verify_seconds = layout.verify_files(
            self.path, self.manifest, verify
        )
        self.config = self._check_config(expected_config)
        self.methods: dict[str, Method] = self._load_methods()
        # The CNN methods run the version's exported models (ONNX Runtime, no torch), or, in a
        # version built before versions stored them, the torch model.
        attach_models(self.path, self.manifest, self.methods)
        unused = () if torch_needed(self.methods) else ("torch",)
        check_packages(self.manifest.get("packages", {}), self.path, unused)
        self._files: list[Any] = []
        self._ref_h5 = self._open(layout.REFERENCES_H5)
        has_local = any(m.kind == "local" for m in self.methods.values())
        self._local_h5 = self._open(layout.LOCAL_H5) if has_local else None
        try:
            self.refs = read_ref_table(self._ref_h5)
            #: rows N: original references, then experiences (what the stored arrays hold)
            self.n_rows = len(self.refs)
            # Stored: each reference's own descriptor; searched: after the method's
            # augmentation over the route (dba), which is the stored matrix itself without.
            #: what this reader has read from disk on demand (rows of the matrices it
            #: does not hold, local features): bytes, rows, calls
            self.read_stats = ReadStats()
            self._stored = {
                mid: self._global_rows(mid, mmap)
                for mid, m in self.methods.items()
                if m.kind == "global"
            }
            self._globals = dict(self._stored)  # augmented once the places are known
            self._offsets = {
                mid: read_local_offsets(self._local_h5, mid)
                for mid, m in self.methods.items()
                if m.kind == "local"
            }
        except (KeyError, ValueError, OSError) as exc:
            raise IndexCorruptError(
                f"{self.path}: missing or damaged dataset ({exc}); run `hmpf-index verify`"
            ) from None
        self._check_shapes()
        #: which rows belong to which place (:class:`~hmpf.index.places.Places`)
        self.places = self._read_places()
        #: places P: what the hierarchy, answers, routes and ground truth count
        self.n = self.places.n
        #: each row's experience set (one log, vehicle and day), None without experiences
        self._sets = experience_sets(self.refs, self.places)
        #: the experience rows each query aligns the sets on (a fixed sample per set)
        self._pairs = None if self._sets is None else pair_sample(self._sets)
        self._globals = {
            mid: x if isinstance(x, DiskRows) else augment_rows(self.methods[mid], x, self.places)
            for mid, x in self._stored.items()
        }
        #: the references' thumbnails (None: a version built before they were stored)
        self.thumbnails = self._open_thumbnails()
        self._faiss: dict[str, Any] = {}
        self._routes: RouteMap | None = None
        self._motion: tuple[tuple[str, MotionSketch] | None] | None = None
        self._profile: ReferenceProfile | None = None
        k1 = self.config.tiers[0].k
        self.approx_k = approx_k or max(256, 4 * k1)
        self._sample = np.unique(
            np.linspace(0, max(self.n_rows - 1, 0), min(self.n_rows, SAMPLE_SIZE))
            .round()
            .astype(np.int64)
        )
        # The sample every approximate tier-1 search scores exactly stays resident (a fixed
        # SAMPLE_SIZE x D per method, whatever the map's size).
        self._sample_rows = {
            mid: np.asarray(x[self._sample])
            for mid, x in self._globals.items()
            if mid in self.config.tiers[0].methods and not self.is_exact(mid)
        }
        #: decoded local features of recent candidates (bounded in bytes)
        self.local_cache = LruCache(local_cache_bytes)

    # -- opening and checks -------------------------------------------------------------------
    def on_demand(self, mid: str) -> bool:
        """Whether global method ``mid``'s rows are read from disk when a query needs them,
        rather than held in memory: every global method that never scores the whole
        database exactly (one of a later tier only, or of tier 1 through an approximate
        FAISS type, whose candidates and sample are re-scored exactly) and has no route
        augmentation (``dba`` averages neighbours when the version loads)."""
        m = self.methods[mid]
        if m.kind != "global" or augments(m):
            return False
        return mid not in self.config.tiers[0].methods or not self.is_exact(mid)

    def _global_rows(self, mid: str, mmap: bool) -> np.ndarray | DiskRows:
        """Method ``mid``'s stored matrix: on demand (:class:`~hmpf.index.rows.DiskRows`)
        when :meth:`on_demand` and stored contiguously, else as
        :func:`~hmpf.index.storage.read_global` gives it (memory-mapped or in memory)."""
        if mmap and self.on_demand(mid):
            rows = disk_rows(self._ref_h5["global"][mid], self.read_stats)
            if rows is not None:
                return rows
        return read_global(self._ref_h5, mid, mmap)

    def _open(self, name: str) -> Any:
        f = open_h5(self.path / name)
        self._files.append(f)
        return f

    def _check_config(self, expected: HierarchyConfig | None) -> HierarchyConfig:
        entry = self.manifest.get("config", {})
        try:
            config = parse_config(entry.get("resolved"), f"{self.path / layout.MANIFEST}:config")
        except ConfigError as exc:
            raise IndexVersionError(
                f"{self.path}: this hmpf cannot honour the index's config ({exc}); rebuild it"
            ) from None
        if config.digest() != entry.get("sha256"):
            raise IndexCorruptError(
                f"{self.path / layout.MANIFEST}: config hash does not match the stored config"
            )
        if expected is not None and expected.digest() != config.digest():
            raise IndexVersionError(
                f"{self.path}: built for config {config.name!r} ({config.digest()[:12]}), "
                f"expected {expected.name!r} ({expected.digest()[:12]}); rebuild the index "
                "with this config or point at the matching index"
            )
        # A version built without acceptance (before its preset shipped a model) gets the
        # shipped model of its hierarchy: the identity (digest) is the same.
        return with_shipped_acceptance(config)

    def _load_methods(self) -> dict[str, Method]:
        methods = build_methods(self.config)
        info = self.manifest.get("methods", {})
        state_file = self.path / layout.STATE_H5
        states = read_state(state_file) if state_file.exists() else {}
        for mid, m in methods.items():
            entry = info.get(mid)
            if entry is None:
                raise IndexCorruptError(
                    f"{self.path / layout.MANIFEST}: no entry for method {mid!r}"
                )
            if str(entry.get("version")) != str(type(m).version):
                raise IndexVersionError(
                    f"{self.path}: method {mid!r} was built with code version "
                    f"{entry.get('version')}, this hmpf has {type(m).version}; rebuild the index"
                )
            if mid in states:
                m.load_state(states[mid])
            elif m.requires_fit():
                raise IndexCorruptError(f"{state_file}: no fitted parameters for {mid!r}")
            if m.cache_key() != entry.get("cache_key"):
                raise IndexCorruptError(
                    f"{self.path}: method {mid!r} does not match the manifest (parameters or "
                    "fitted state changed); run `hmpf-index verify`"
                )
        return methods

    def _check_shapes(self) -> None:
        n = self.n_rows
        expect = self.manifest.get("images", {}).get("count")
        if expect != n or len(self.refs.sha256) != n:
            raise IndexCorruptError(
                f"{self.path / layout.REFERENCES_H5}: {n} names, manifest says {expect}"
            )
        for col, v in self.refs.meta.items():
            if len(v) != n:
                raise IndexCorruptError(
                    f"{self.path / layout.REFERENCES_H5}: meta/{col} has {len(v)}"
                )
        for mid, mat in self._globals.items():
            dim = self.manifest["methods"][mid].get("dim")
            if mat.ndim != 2 or mat.shape[0] != n or (dim is not None and mat.shape[1] != dim):
                raise IndexCorruptError(
                    f"{self.path / layout.REFERENCES_H5}: global/{mid} has shape {mat.shape}, "
                    f"expected ({n}, {dim})"
                )
        local_h5 = self.path / layout.LOCAL_H5
        for mid, offs in self._offsets.items():
            for key, o in offs.items():
                rows = self._local_rows(mid, key, o)
                if o is not None and (
                    len(o) != n + 1 or o[0] != 0 or (np.diff(o) < 0).any() or o[-1] != rows
                ):
                    raise IndexCorruptError(
                        f"{local_h5}: local/{mid}/{key} offsets are inconsistent"
                    )
                if o is None and rows != n:
                    raise IndexCorruptError(
                        f"{local_h5}: local/{mid}/{key} has {rows} blocks for {n}"
                    )

    def _read_places(self) -> Places:
        """The grouping of rows into places, checked against the ``place`` column's invariant
        and the manifest's ``places`` entry (absent: no experiences)."""
        where = str(self.path / layout.REFERENCES_H5)
        places = Places.from_column(self.refs.meta.get("place"), self.n_rows, where)
        entry = self.manifest.get("places")
        if entry is not None:
            count = entry.get("count") if isinstance(entry, dict) else None
            if count != places.n or entry.get("experiences", 0) != self.n_rows - places.n:
                raise IndexCorruptError(
                    f"{where}: {places.n} places and {self.n_rows - places.n} experiences, "
                    f"the manifest says {entry}"
                )
        return places

    def map_prior(self) -> float | None:
        """The version's map-level prior (the manifest's ``map_prior``: the log-odds of its
        config's recall@1 on pseudo-queries of the references, ``hmpf-index build
        --map-prior``); None when the version has none, none could be computed, or it was
        computed under another config.

        Raises:
            IndexCorruptError: an entry whose value is not a finite number.
        """
        entry = self.manifest.get("map_prior")
        if not isinstance(entry, dict) or entry.get("config_sha256") != self.config.digest():
            return None
        try:
            return stored_map_prior(entry.get("map_prior"))
        except ValueError as exc:
            raise IndexCorruptError(f"{self.path / layout.MANIFEST}: {exc}") from None

    def _open_thumbnails(self) -> ThumbnailStore | None:
        entry = self.manifest.get("thumbnails")
        if not isinstance(entry, dict) or not entry.get("file"):
            return None
        name = str(entry["file"])
        if name not in self.manifest.get("files", {}):  # only a file the checksums cover
            raise IndexCorruptError(
                f"{self.path / layout.MANIFEST}: thumbnails file {name!r} is not in its files"
            )
        return ThumbnailStore(self._open(name), self.n_rows)

    def thumbnail(self, i: int) -> bytes | None:
        """Row ``i``'s thumbnail (JPEG bytes; place ``i``'s for ``i < n``), None when the
        version has none."""
        return None if self.thumbnails is None else self.thumbnails.get(i)

    def thumbnail_column(self) -> Ragged:
        """Every row's thumbnail (empty entries without one), for add / remove."""
        if self.thumbnails is None:
            return empty_thumbnails(self.n_rows)
        return self.thumbnails.column()

    def _local_rows(self, mid: str, key: str, offsets: np.ndarray | None) -> int:
        g = self._local_h5["local"][mid][key]  # type: ignore[index]
        return int(g["blocks" if offsets is None else "data"].shape[0])

    def close(self) -> None:
        """Close the HDF5 files (memory-mapped matrices stay valid while referenced)."""
        for f in self._files:
            f.close()
        self._files.clear()
        for x in getattr(self, "_stored", {}).values():
            if isinstance(x, DiskRows):
                x.close()

    def __enter__(self) -> IndexReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return self.n

    # -- places and experiences ----------------------------------------------------------------
    @property
    def has_experiences(self) -> bool:
        """Whether some place holds more than its original reference."""
        return self.places.has_experiences

    @property
    def place_names(self) -> list[str]:
        """The places' names (their original references'), place order: what ground truth
        and recall are computed over."""
        return self.refs.names[: self.n]

    def experience(self, row: int) -> Experience:
        """Row ``row`` described: name, original or fleet experience, its provenance."""
        if not 0 <= row < self.n_rows:
            raise IndexError(f"row {row} out of range 0 .. {self.n_rows - 1}")
        return experience_of_row(self.refs, self.places, row)

    def experiences(self, place: int) -> list[Experience]:
        """A place's stored images: its original reference first, then its experiences."""
        if not 0 <= place < self.n:
            raise IndexError(f"place {place} out of range 0 .. {self.n - 1}")
        return [self.experience(int(r)) for r in self.places.rows(place)]

    def matched_rows(self, score_fn: ScoreFn) -> np.ndarray | None:
        """(P,) per place, the row (experience) that matched it for the query ``score_fn``
        (from :meth:`scorer`) has scored: the winner of the final tier's first method, else
        of the next method that scored the place (the final tier's, then earlier tiers'); -1
        where none did. None in a version without experiences (every place is its row)."""
        if not isinstance(score_fn, PlaceScorer):
            return None
        priority = [m for tier in reversed(self.config.tiers) for m in tier.methods]
        return score_fn.matched_rows(list(dict.fromkeys(priority)))

    # -- data access -------------------------------------------------------------------------
    def hierarchy(self) -> Hierarchy:
        """The :class:`~hmpf.hierarchy.Hierarchy` the index was built for."""
        return Hierarchy(self.config, self.methods)

    def route_map(self) -> RouteMap:
        """The mapped routes over the places for sequence filtering (:mod:`hmpf.sequence`):
        the ``sequence`` column's routes, ordered by ``timestamp`` where given, junctions from
        ``lat``/``lon`` (the places' original references',
        :func:`~hmpf.index.places.route_map_of`; built once per reader)."""
        if self._routes is None:
            self._routes = route_map_of(self.refs.meta, self.n, self.config)
        return self._routes

    def motion_sketch(self) -> tuple[str, MotionSketch] | None:
        """``(method id, sketch)``: the :class:`~hmpf.sequence.MotionSketch` of the places
        for a config whose sequence filter weighs motion (``stop_factor`` < 1), over tier
        1's first global method; None when the filter weighs none or the map gives no
        sketch. Built once per reader from up to 1,024 places' rows."""
        if self._motion is None:
            made = None
            if self.config.sequence_params().motion:
                mid = sketch_method(self.methods, self.config.tiers[0].methods)
                if mid is not None and mid in self._globals:
                    sketch = MotionSketch.from_references(self._globals[mid], self.route_map())
                    made = None if sketch is None else (mid, sketch)
            self._motion = (made,)
        return self._motion[0]

    def reference_profile(self) -> ReferenceProfile:
        """The places' :class:`~hmpf.confidence.ReferenceProfile` for the first tier's
        global methods (what absolute confidence evidence compares with): the one the version
        stores (``profile.h5``, computed when it was written), else (a version written before
        versions stored it) built from the places' descriptors
        (:func:`~hmpf.index.places.places_profile`, about ``256 x P`` scores per method).
        Read or built once per reader.

        Raises:
            IndexCorruptError: the stored profile is unreadable, or not of this version's
                tier-1 global methods and places (:func:`~hmpf.index.storage.stored_profile`).
        """
        if self._profile is None:
            tier1 = [m for m in self.config.tiers[0].methods if m in self._globals]
            stored = stored_profile(self.path, self.manifest, tier1, self.n)
            profile = (
                stored
                if stored is not None
                else places_profile(self.config, self.methods, self._globals, self.route_map())
            )
            self._profile = dataclasses.replace(profile, map_prior=self.map_prior())
        return self._profile

    def extract_query(
        self,
        image: np.ndarray,
        ms: dict[str, float] | None = None,
        executor: Executor | None = None,
    ) -> dict[str, Any]:
        """Every method's feature of one RGB ``uint8`` query image.

        CNN methods on the same backbone and input size share one forward pass; with an
        ``executor`` the forward-pass groups and other methods run as parallel tasks on it
        (:func:`hmpf.features.extract_query`). When ``ms`` is given, each method's time (ms;
        a shared forward pass is counted once, in the first method of its group) is stored.
        """
        return extract_query(self.methods, image, ms, executor)

    def global_matrix(self, mid: str) -> np.ndarray | DiskRows:
        """(N, D) stored vectors of a global method (every row), in the dtype the method
        produced: an array, or rows read on demand (:meth:`on_demand`; index it, or
        ``np.asarray`` it to read everything)."""
        return self._globals[mid]

    def local_features(self, mid: str, idx: np.ndarray) -> list[Any]:
        """Features of rows ``idx`` of a local method, read without loading the others."""
        idx = np.asarray(idx, dtype=np.int64)
        method = self.methods[mid]
        found: dict[int, Any] = {}
        for i in dict.fromkeys(idx.tolist()):
            hit, value = self.local_cache.lookup((mid, i))
            if hit:
                found[i] = value
        todo = np.array([i for i in dict.fromkeys(idx.tolist()) if i not in found], np.int64)
        if len(todo):
            per_key = {
                key: read_local_items(self._local_h5, mid, key, todo, o)
                for key, o in self._offsets[mid].items()
            }
            for j, i in enumerate(todo.tolist()):
                arrays = {k: v[j] for k, v in per_key.items()}
                self.read_stats.add(1, sum(int(np.asarray(a).nbytes) for a in arrays.values()))
                found[i] = method.from_arrays(arrays)
                self.local_cache.put((mid, i), found[i], _nbytes(found[i]))
        return [found[i] for i in idx.tolist()]

    def columns(self, mid: str) -> Columns:
        """Every row's stored arrays of one method (for add / remove)."""
        if self.methods[mid].kind == "global":
            return np.asarray(self._stored[mid])
        return read_local_columns(self._local_h5, mid)

    def faiss_info(self, mid: str) -> dict[str, Any] | None:
        return self.manifest["methods"][mid].get("faiss")

    def faiss_index(self, mid: str) -> Any:
        """The FAISS index of a tier-1 global method (loaded on first use), or None."""
        info = self.faiss_info(mid)
        if info is None:
            return None
        if mid not in self._faiss:
            if info["file"] is None:
                index = self._flat(mid, MetricSpec(**info["metric"]))
            else:
                index = read_faiss(
                    self.path / info["file"], info.get("params", ""), mmap=self._mmap
                )
            if index.ntotal != self.n_rows or index.d != self._globals[mid].shape[1]:
                raise IndexCorruptError(
                    f"{self.path / (info['file'] or layout.REFERENCES_H5)}: {index.ntotal} x "
                    f"{index.d} vectors, "
                    f"expected {self.n_rows} x {self._globals[mid].shape[1]}"
                )
            self._faiss[mid] = index
        return self._faiss[mid]

    def approximate_methods(self) -> list[str]:
        """Tier 1's global methods searched through an approximate FAISS type."""
        return [
            m
            for m in self.config.tiers[0].methods
            if self.methods[m].kind == "global" and not self.is_exact(m)
        ]

    def set_faiss_params(self, params: Mapping[str, str]) -> None:
        """Search tier 1's approximate FAISS indexes with ``params`` on top of the version's
        stored search parameters (which these override where both name one): method id, or
        ``"*"`` for every approximate method (none in an exact version), -> a FAISS search
        parameter string (:func:`hmpf.index.ann.set_search_params`, e.g. ``nprobe=64`` or
        ``k_factor_front=2``). A method's own entry replaces ``"*"`` for it (as in
        ``hmpf-index build --faiss-params``; an empty one keeps the stored parameters). A
        method that is not approximate is a :class:`~hmpf.errors.ConfigError`, a parameter
        its type lacks an :class:`~hmpf.index.layout.IndexBuildError` naming the method."""
        approximate = self.approximate_methods()
        unknown = sorted(set(params) - {"*", *approximate})
        if unknown:
            raise ConfigError(
                f"faiss_params: {', '.join(map(repr, unknown))} not an approximate tier-1 "
                f"method of {self.path} (those: {', '.join(approximate) or 'none'})"
            )
        for mid in approximate:
            extra = params.get(mid, params.get("*", ""))
            if not extra:
                continue
            try:
                set_search_params(self.faiss_index(mid), extra)
            except IndexBuildError as exc:
                raise IndexBuildError(f"faiss_params of method {mid!r}: {exc}") from None

    def _flat(self, mid: str, metric: MetricSpec) -> Any:
        """An exact FAISS Flat index over the stored matrix (built in memory)."""
        faiss = faiss_module()
        x = np.ascontiguousarray(self._globals[mid], dtype=np.float32)
        kinds = {"l2": faiss.METRIC_L2, "l1": faiss.METRIC_L1, "ip": faiss.METRIC_INNER_PRODUCT}
        index = faiss.IndexFlat(x.shape[1], kinds[metric.kind])
        index.add(x)
        return index

    def is_exact(self, mid: str) -> bool:
        """Tier 1 of ``mid`` scores every reference exactly (no approximate FAISS type)."""
        info = self.faiss_info(mid)
        return info is None or bool(info["exact"])

    def search(
        self, mid: str, query: Any, k: int, *, rescore: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """Top ``k`` rows of a global method through FAISS.

        Returns:
            ``(ids, raw)``: (k,) int64 row indices best first and their raw scores in
            the method's units (re-scored exactly when the FAISS metric is only a proxy,
            unless ``rescore`` is False: then FAISS's order and values, for a caller that
            re-scores the rows itself).
        """
        index = self.faiss_index(mid)
        if index is None:
            raise IndexCorruptError(f"{self.path}: method {mid!r} has no FAISS index")
        metric = MetricSpec(**self.faiss_info(mid)["metric"])  # type: ignore[index]
        q = np.ascontiguousarray(np.asarray(query, dtype=np.float32).reshape(1, -1))
        values, ids = search_faiss(index, q, min(k, self.n_rows))
        keep = ids[0] >= 0
        ids, raw = ids[0][keep].astype(np.int64), to_raw(values[0][keep], metric)
        if metric.proxy and rescore:
            method = self.methods[mid]
            raw = method.scores(query, self._globals[mid], ids)
            order = np.argsort(-raw if method.higher_is_better else raw, kind="stable")
            ids, raw = ids[order], raw[order]
        return ids, raw

    # -- scoring -------------------------------------------------------------------------------
    def scorer(self, query: Mapping[str, Any]) -> ScoreFn:
        """A :data:`~hmpf.hierarchy.ScoreFn` of one query's features against the places.

        Without experiences it is :meth:`row_scorer` itself (rows are places: results are
        exactly those of a version built before experiences existed). With them, a
        :class:`~hmpf.index.places.PlaceScorer` over it: a place scores by its best
        experience, per method, and remembers which row won (:meth:`matched_rows`).
        """
        rows = self.row_scorer(query)
        if not self.has_experiences:
            return rows
        return place_scorer(rows, self.places, self.methods, self._sets, self._pairs)

    def row_scorer(self, query: Mapping[str, Any]) -> ScoreFn:
        """A :data:`~hmpf.hierarchy.ScoreFn` of one query's features against every row.

        Mirrors :func:`hmpf.hierarchy.feature_scorer` (whole-database scores remembered and
        gathered for later tiers), so exact indexes give identical results.
        """
        memo: dict[str, np.ndarray | Filled] = {}

        def score_fn(mid: str, subset: np.ndarray | None) -> np.ndarray | Filled:
            if subset is None:
                if mid not in memo:
                    memo[mid] = self._full_scores(mid, query[mid])
                return memo[mid]
            if mid in memo and self.is_exact(mid):
                return memo[mid][subset]
            return self._subset_scores(mid, query[mid], np.asarray(subset, dtype=np.int64))

        return score_fn

    def _full_scores(self, mid: str, q: Any) -> np.ndarray | Filled:
        method = self.methods[mid]
        if method.kind == "local":
            refs = method.stack(self.local_features(mid, np.arange(self.n_rows)))
            return method.scores(q, refs, None)
        if self.is_exact(mid):
            return method.scores(q, self._globals[mid], None)
        return self._approx_scores(mid, q)

    def _approx_scores(self, mid: str, q: Any) -> Filled:
        """Tier 1 of an approximate method: FAISS's candidates and the fixed sample scored
        exactly (the sample from its resident rows, the other candidates' rows read from
        the stored matrix), every other row the worst of those scores: a
        :class:`~hmpf.fusion.Filled` vector (``np.asarray`` of it: the whole array)."""
        method = self.methods[mid]
        ids, _ = self.search(mid, q, self.approx_k, rescore=False)
        extra = np.setdiff1d(ids, self._sample)
        sampled = method.scores(q, self._sample_rows[mid], None)
        exact = np.concatenate([sampled, method.scores(q, self._globals[mid], extra)])
        worst = float(np.min(exact) if method.higher_is_better else np.max(exact))
        index = np.concatenate([self._sample, extra])
        order = np.argsort(index, kind="stable")
        return Filled(self.n_rows, index[order], np.asarray(exact, np.float64)[order], worst)

    def _subset_scores(self, mid: str, q: Any, subset: np.ndarray) -> np.ndarray:
        method = self.methods[mid]
        if method.kind == "global":
            return method.scores(q, self._globals[mid], subset)
        return method.scores(q, method.stack(self.local_features(mid, subset)), None)
