"""The query engine: one loaded index version, the hierarchy over it, and a bounded pool.

* The index and its models load once (at start-up and on reload); a request takes a lease on
  the version that is current when it starts and keeps it to the end, so a reload never
  changes the data under a running query. A retired version is closed when its last lease
  ends.
* A query runs on one of ``workers`` query threads (decoding, the hierarchy); its extraction
  is split into tasks (one per CNN forward-pass group, one per other method) on a compute
  pool of ``workers`` threads, each limited to ``threads_per_worker`` ONNX Runtime / OpenCV
  / BLAS threads (the CNN methods run the ONNX models the version stores,
  :mod:`hmpf.index.models`: a server needs no torch). A lone query thus runs its extraction
  tasks in parallel (up to one core per task), and under load the compute pool bounds the
  process so that concurrent queries do not oversubscribe the cores. At most
  ``workers + queue`` slots are admitted at once (a query takes one, a batch at most ``workers``,
  running its images in that many lanes); beyond that :meth:`Engine.admit` refuses and the
  API answers 503 + Retry-After. Slots and leases are released by the pool threads when
  their work ends, so a client that disconnects never frees capacity that is still in use.
* Verification (:attr:`Loaded.verification`): a version is opened by its verification stamp
  when it has a matching one (:func:`hmpf.index.layout.stamp_matches`: its files are, inode
  and change times, those a full sha256 check passed at publish or in ``hmpf-index
  verify``), so that it answers within seconds of the start whatever its size; otherwise
  every byte is hashed before it answers (on every core), and a corrupt version is refused
  (start-up exits, a reload keeps the loaded version). A version opened by its stamp is then
  checked in full anyway, on one background thread at low priority (one check at a time),
  because a stamp cannot see a byte changed below the file system (a failing disk) or a
  forged stamp. If that check finds a damaged file, the version is marked ``corrupt``:
  its stamp is deleted, the error logged and counted (:attr:`Engine.on_corrupt`), and no
  new query is answered from it: :meth:`Engine.lease` raises :class:`IndexVersionCorrupt`
  (the API's 503 ``index_corrupt``; ``/readyz`` says not ready), unless the version it
  replaced in a reload is still held, sound: a version opened by its stamp on a reload keeps
  the previous sound version open until its check passes (memory for both meanwhile, as
  during any reload), and a failed check switches back to that one. Queries already
  running when the damage is found finish on the version they started on.
"""

from __future__ import annotations

import asyncio
import ctypes
import logging
import math
import os
import threading
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from hmpf.acceptance import DEFAULT_ACCEPT_THRESHOLD, Policy
from hmpf.confidence import ReferenceProfile
from hmpf.datasets import haversine_m
from hmpf.errors import ConfigError
from hmpf.hierarchy import Hierarchy, HierarchyResult, ScoreFn
from hmpf.index import layout
from hmpf.index.reader import IndexReader
from hmpf.runtime import set_compute_threads
from hmpf.sequence import MotionSketch, SequenceFilter
from service.track import binding_digest

__all__ = [
    "DEFAULT_ACCEPT_THRESHOLD",
    "VERIFICATION_STATES",
    "Acceptance",
    "Engine",
    "IndexVersionCorrupt",
    "Loaded",
    "Prior",
    "confidence",
]

log = logging.getLogger("hmpf.service")
T = TypeVar("T")
#: What one job of a lane ended with: (True, its value) or (False, the exception it raised).
JobResult = tuple[bool, Any]
#: How a loaded version's files were verified (:attr:`Loaded.verification`): ``full``, every
#: sha256 before it answered; ``checking``, opened by its verification stamp and answering
#: while the full check runs in the background; ``passed``, that check found every byte as
#: the manifest lists it; ``corrupt``, it did not: the version answers no query.
VERIFICATION_STATES = ("full", "checking", "passed", "corrupt")
#: Niceness of the background check's thread (Linux: per thread), below the query threads.
CHECK_NICENESS = 10


class IndexVersionCorrupt(Exception):
    """The loaded version failed its background check: it answers no query."""

    def __init__(self, version: str) -> None:
        super().__init__(f"index version {version} is corrupt")
        self.version = version


def confidence(quality: float, n: int) -> float:
    """The match's Combined z-score over ``n`` candidates as a fraction of the largest
    possible one, ``(n - 1) / sqrt(n)`` (one candidate far above all others equal): 1 when
    the match stands alone, 0 when it is no better than the mean (or ``n < 2``)."""
    if n < 2 or not math.isfinite(quality):
        return 0.0
    return float(min(1.0, max(0.0, quality / ((n - 1) / math.sqrt(n)))))


@dataclass(frozen=True)
class Prior:
    """A GPS prior: only places within ``radius_m`` of (lat, lon) are candidates."""

    lat: float
    lon: float
    radius_m: float


#: How a version's answers are accepted: the core's one policy (:mod:`hmpf.acceptance`).
Acceptance = Policy


@dataclass
class Loaded:
    """One opened index version and what the queries need from it.

    ``sequence`` is the sequence filter over the version's routes and ``binding`` the digest
    that ties a vehicle's track token to this version (:mod:`service.track`); ``acceptance``
    the rules that decide ``accepted`` (:class:`hmpf.acceptance.Policy`) and ``profile`` the
    references' profile (absolute evidence: the models and the filter's off-map state read
    it; None only for a version opened without it).
    """

    reader: IndexReader
    hierarchy: Hierarchy
    threshold: float
    loaded_at: float
    sequence: SequenceFilter
    binding: bytes
    acceptance: Acceptance
    leases: int = 0
    retired: bool = False
    lat: np.ndarray | None = field(default=None, repr=False)
    lon: np.ndarray | None = field(default=None, repr=False)
    profile: ReferenceProfile | None = field(default=None, repr=False)
    #: (method id, sketch) of the frames' motion, for a sequence filter that weighs it
    #: (:meth:`hmpf.index.reader.IndexReader.motion_sketch`); None: it weighs none
    motion: tuple[str, MotionSketch] | None = field(default=None, repr=False)
    #: whether the version stores the map prior its models read (False: the models'
    #: fallback stands in, :meth:`hmpf.acceptance.Policy.with_map_prior`); None: no model
    #: reads it
    map_prior_stored: bool | None = None
    #: how its files were verified, one of :data:`VERIFICATION_STATES`
    verification: str = "full"
    #: what the background check found, paths relative to the version (empty: nothing)
    problems: list[str] = field(default_factory=list)
    #: seconds the background check took (None: not run, or not finished)
    check_seconds: float | None = None
    #: set to stop the background check (the version is retired)
    stop_check: threading.Event = field(default_factory=threading.Event, repr=False)

    @classmethod
    def open(
        cls,
        root: Path,
        threshold: float | None,
        verify: layout.VerifyMode = "stamp",
        approx_k: int | None = None,
        faiss_params: Mapping[str, str] | None = None,
    ) -> Loaded:
        """Open the version ``CURRENT`` names, its files verified before anything is read
        from them (``verify``, :func:`hmpf.index.layout.verify_files`): by their
        verification stamp when it matches (:attr:`verification` ``checking``: the caller
        runs the full check), else every file against the manifest's sha256 (a corrupt
        version raises :class:`~hmpf.index.IndexCorruptError`: start exits 2, reload
        answers 409). ``faiss_params``: tier 1's FAISS search parameters on top of the
        version's own (:meth:`IndexReader.set_faiss_params`; bad ones raise as well)."""
        reader = IndexReader(root, verify=verify, approx_k=approx_k)
        if faiss_params:
            try:
                reader.set_faiss_params(faiss_params)
            except BaseException:
                reader.close()
                raise
        verification = "checking" if reader.verified_by == "stamp" else "full"
        return cls.over(reader, threshold, verification)

    @classmethod
    def over(cls, reader: Any, threshold: float | None, verification: str = "full") -> Loaded:
        """A :class:`Loaded` over an open ``reader`` (an :class:`IndexReader`, or a view of
        the same shape such as a sharded map's), closed again when this fails."""
        try:
            params = reader.config.sequence_params()
            # A view of another shape (a sharded map's) may not sketch the frames' motion:
            # refused rather than answering otherwise than the unsharded version would.
            sketch_of = getattr(reader, "motion_sketch", None)
            if params.motion and sketch_of is None:
                raise ConfigError(
                    f"{reader.path}: its sequence filter weighs motion (sequence.stop_factor "
                    f"{params.stop_factor:g}, slow_factor {params.slow_factor:g}), which this "
                    "kind of map cannot sketch; serve the unsharded version or set both to 1"
                )
            acceptance = Policy.of(
                reader.config.acceptance,
                threshold=threshold,
                lock_mass=params.lock_mass,
                label=str(reader.path),
            )
            # Always: the models read it, and the sequence filter's off-map state weighs
            # each frame's absolute evidence with it.
            stored = reader.reference_profile()
            profile = acceptance.with_map_prior(stored, str(reader.path))
            if profile is not stored:
                log.warning(
                    "%s stores no map prior: the acceptance models read the conservative "
                    "fallback %+.2f, so fewer answers will be accepted; build the version with "
                    "hmpf-index build --map-prior",
                    reader.path,
                    acceptance.map_prior_fallback,
                )
            # Positions are the places' (their original references', rows 0 .. P-1).
            meta, P = reader.refs.meta, reader.n
            lat = None if meta.get("lat") is None else meta["lat"][:P]
            lon = None if meta.get("lon") is None else meta["lon"][:P]
            has_pos = lat is not None and lon is not None and bool(np.isfinite(lat).any())
            motion = sketch_of() if sketch_of is not None else None
            return cls(
                reader,
                reader.hierarchy(),
                acceptance.threshold,
                time.time(),
                SequenceFilter(reader.route_map(), params),
                binding_digest(reader.manifest, params),
                acceptance,
                lat=np.asarray(lat, dtype=np.float64) if has_pos else None,
                lon=np.asarray(lon, dtype=np.float64) if has_pos else None,
                profile=profile,
                motion=motion,
                map_prior_stored=(profile is stored) if acceptance.needs_map_prior else None,
                verification=verification,
            )
        except BaseException:
            reader.close()
            raise

    @property
    def version(self) -> str:
        return self.reader.version

    @property
    def sound(self) -> bool:
        """Every byte checked and found as listed (before it answered, or in the background)."""
        return self.verification in ("full", "passed")

    @property
    def has_positions(self) -> bool:
        return self.lat is not None

    def within(self, prior: Prior) -> np.ndarray:
        """Ids of the places within the prior's radius (positions unknown: none)."""
        assert self.lat is not None and self.lon is not None
        d = haversine_m(prior.lat, prior.lon, self.lat, self.lon)
        return np.flatnonzero(np.isfinite(d) & (d <= prior.radius_m)).astype(np.int64)


def _lower_priority() -> None:
    """Give the calling thread :data:`CHECK_NICENESS` (Linux; elsewhere nothing)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), CHECK_NICENESS)
    except (AttributeError, OSError):  # pragma: no cover - not Linux, or not allowed
        pass


def _relative(line: str, version_dir: Path) -> str:
    """A problem line with the version folder's path dropped (answers must not show where the
    index lies on the server)."""
    return line.replace(f"{version_dir}/", "").replace(str(version_dir), version_dir.name)


def restricted(score_fn: ScoreFn, allowed: np.ndarray) -> ScoreFn:
    """A score function over the sub-database ``allowed`` (local index -> place id)."""

    def fn(mid: str, subset: np.ndarray | None) -> np.ndarray:  # a subset: never Filled
        return np.asarray(score_fn(mid, allowed if subset is None else allowed[subset]))

    return fn


class Engine:
    """Holds the current index version and runs queries on a bounded thread pool."""

    def __init__(
        self,
        root: Path,
        *,
        workers: int,
        queue: int,
        threads_per_worker: int,
        accept_threshold: float | None = None,
        approx_k: int | None = None,
        faiss_params: Mapping[str, str] | None = None,
    ) -> None:
        self.root = Path(root)
        #: rows an approximate tier-1 search re-scores (None: the reader's default)
        self.approx_k = approx_k
        #: tier 1's FAISS search parameters on top of each version's own
        self.faiss_params = dict(faiss_params or {})
        self.workers = workers
        self.capacity = workers + queue
        self.threads = threads_per_worker
        self.accept_threshold = accept_threshold
        self.admitted = 0  # slots held by running + waiting lanes (under _lock)
        self.running = 0
        self._lock = threading.Lock()
        self._reload_lock = asyncio.Lock()
        self._current: Loaded | None = None
        #: the previous sound version, held while the current one's background check runs
        self._fallback: Loaded | None = None
        #: the background check's thread (one at a time)
        self._checker: threading.Thread | None = None
        #: called with a version the background check found corrupt (the app counts it)
        self.on_corrupt: Callable[[Loaded], None] | None = None
        self._pool = ThreadPoolExecutor(
            max_workers=workers, thread_name_prefix="hmpf-query", initializer=self._init_thread
        )
        self.compute = ThreadPoolExecutor(
            max_workers=workers, thread_name_prefix="hmpf-compute", initializer=self._init_thread
        )

    # -- lifecycle ----------------------------------------------------------------------------
    def _init_thread(self) -> None:
        set_compute_threads(self.threads)

    def load(self) -> Loaded:
        """Open the index's current version (blocking) and make it current.

        A version opened by its verification stamp gets its full check on the background
        thread; meanwhile the previous version, if sound, stays open to take over should
        that check fail (see the module's docstring).
        """
        loaded = self._open()
        try:
            self._warm_up(loaded)
        except BaseException:
            loaded.reader.close()
            raise
        with self._lock:
            old, self._current = self._current, loaded
            keep = None if loaded.sound else self._sound_fallback(old)
            for x in {id(x): x for x in (old, self._fallback) if x is not None}.values():
                if x is not keep:
                    self._retire(x)
            self._fallback = keep
        if loaded.verification == "checking":
            self._start_check(loaded)
        self._log_loaded(loaded)
        return loaded

    def _open(self) -> Loaded:
        """The index's current version, opened (what :meth:`load` makes current)."""
        return Loaded.open(
            self.root,
            self.accept_threshold,
            approx_k=self.approx_k,
            faiss_params=self.faiss_params,
        )

    def _log_loaded(self, loaded: Loaded) -> None:
        how = (
            "files trusted by their verification stamp; full check started in the background"
            if loaded.verification == "checking"
            else f"files verified in {loaded.reader.verify_seconds or 0.0:.2f} s"
        )
        # what runs the CNN methods' passes: the process's runtime, torch for a backbone
        # without an exported model, openvino-bf16 for a bf16 method
        cnn = {
            m.session_runtime()
            for m in loaded.reader.methods.values()
            if hasattr(m, "session_runtime")
        }
        log.info(
            "index %s version %s loaded (%d references, %d experiences; %s; CNN runtime %s)",
            self.root,
            loaded.version,
            loaded.reader.n,
            loaded.reader.n_rows - loaded.reader.n,
            how,
            ", ".join(sorted(cnn)) or "none (no CNN method)",
        )

    def _sound_fallback(self, old: Loaded | None) -> Loaded | None:
        """The version to hold while a new one's check runs: the one it replaces if sound,
        else the one held already (under ``_lock``)."""
        return old if old is not None and old.sound else self._fallback

    def _retire(self, loaded: Loaded) -> None:
        """No new lease on ``loaded``; stop its check; close it now or at its last release
        (under ``_lock``)."""
        loaded.retired = True
        loaded.stop_check.set()
        weakref.finalize(loaded, _trim_soon)
        if loaded.leases == 0:
            loaded.reader.close()

    # -- the background check -----------------------------------------------------------------
    def _start_check(self, loaded: Loaded) -> None:
        """Run the full check of ``loaded`` on the background thread (the check of the
        version it replaced, retired, has been told to stop: waited for first)."""
        previous = self._checker
        if previous is not None:
            previous.join(timeout=30)
            if previous.is_alive():  # pragma: no cover - a read blocked for 30 s
                log.warning("the previous background check has not stopped yet")
        self._checker = threading.Thread(
            target=self._check, args=(loaded,), name="hmpf-verify", daemon=True
        )
        self._checker.start()

    def check_done(self, timeout: float | None = None) -> bool:
        """Wait for the background check (if any) to end; whether none is running."""
        checker = self._checker
        if checker is not None:
            checker.join(timeout)
        return checker is None or not checker.is_alive()

    def _check(self, loaded: Loaded) -> None:
        """Every byte of ``loaded`` against its manifest, on this one thread, at a lower
        priority than the queries; the outcome goes to :meth:`_checked`."""
        _lower_priority()
        reader = loaded.reader
        t = time.perf_counter()
        try:
            problems = layout.file_problems(
                reader.path, reader.manifest, workers=1, stop=loaded.stop_check
            )
        except layout.CheckStopped:
            log.info("background check of version %s stopped (replaced)", loaded.version)
            return
        except Exception as exc:  # a file that cannot be read is not served either
            log.exception("background check of version %s failed", loaded.version)
            problems = [f"{reader.path}: cannot be checked ({exc})"]
        loaded.check_seconds = time.perf_counter() - t
        self._checked(loaded, [_relative(line, reader.path) for line in problems])

    def _checked(self, loaded: Loaded, problems: list[str]) -> None:
        """Record the background check's outcome: ``passed`` (the held previous version is
        let go), or ``corrupt`` (the held previous version, if any, answers again; the stamp
        is deleted; logged and counted). Nothing for a version no longer current."""
        with self._lock:
            if loaded is not self._current or loaded.retired:
                return
            fallback, self._fallback = self._fallback, None
            if not problems:
                loaded.verification = "passed"
                if fallback is not None:
                    self._retire(fallback)
            else:
                loaded.verification = "corrupt"
                loaded.problems = problems
                if fallback is not None:
                    self._current = fallback
                    self._retire(loaded)
        if not problems:
            log.info(
                "index %s version %s: background check passed (every file matches its "
                "sha256, %.1f s)",
                self.root,
                loaded.version,
                loaded.check_seconds or 0.0,
            )
            return
        layout.remove_stamp(loaded.reader.path)
        log.error(
            "INDEX VERSION %s IS CORRUPT (%s/%s): %s. %s. Run `hmpf-index verify --index %s`, "
            "switch to a sound version with `hmpf-index use VERSION` (or rebuild), then reload",
            loaded.version,
            self.root,
            loaded.version,
            "; ".join(problems),
            f"Version {fallback.version} answers again"
            if fallback is not None
            else "This server answers no query from it (503 index_corrupt; /readyz not ready)",
            self.root,
        )
        if self.on_corrupt is not None:
            try:
                self.on_corrupt(loaded)
            except Exception:  # pragma: no cover - a metric
                log.exception("on_corrupt failed")

    def _warm_up(self, loaded: Loaded) -> None:
        """Load weights and build lazy structures now rather than in the first request: with
        the requests' compute threads, since a CNN model's session (an OpenVINO compile) is
        made per thread count."""
        set_compute_threads(self.threads)  # process-wide, as each pool thread sets it
        rng = np.random.default_rng(0)
        image = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
        feats = loaded.reader.extract_query(image)
        loaded.hierarchy.run(loaded.reader.scorer(feats), loaded.reader.n)

    async def reload(self) -> tuple[str, str]:
        """Switch to the index's current version; returns (old version, new version)."""
        async with self._reload_lock:
            old = self.current.version if self._current else ""
            loop = asyncio.get_running_loop()
            loaded = await loop.run_in_executor(None, self.load)
            return old, loaded.version

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self.compute.shutdown(wait=True, cancel_futures=True)
        with self._lock:
            held = [x for x in (self._current, self._fallback) if x is not None]
            self._current = self._fallback = None
        for x in held:
            x.stop_check.set()
        self.check_done(timeout=30)
        for x in held:
            x.reader.close()

    @property
    def ready(self) -> bool:
        return self._current is not None

    @property
    def current(self) -> Loaded:
        if self._current is None:
            raise RuntimeError("no index loaded")
        return self._current

    # -- leases and admission -----------------------------------------------------------------
    def lease(self) -> Loaded:
        """The current version, held until :meth:`release`.

        Raises:
            IndexVersionCorrupt: it failed its background check (it answers nothing).
        """
        with self._lock:
            loaded = self.current
            if loaded.verification == "corrupt":
                raise IndexVersionCorrupt(loaded.version)
            loaded.leases += 1
            return loaded

    def release(self, loaded: Loaded) -> None:
        with self._lock:
            loaded.leases -= 1
            if loaded.retired and loaded.leases == 0:
                loaded.reader.close()

    def admit(self, n: int = 1) -> bool:
        """Reserve ``n`` query slots, False (nothing reserved) when the pool is full."""
        with self._lock:
            if self.admitted + n > self.capacity:
                return False
            self.admitted += n
            return True

    def done(self, n: int = 1) -> None:
        with self._lock:
            self.admitted -= n

    @property
    def queued(self) -> int:
        return max(0, self.admitted - self.running)

    def start(
        self, jobs: Sequence[Callable[[Loaded], T]], lanes: int = 1
    ) -> tuple[list[Future[None]], list[JobResult]]:
        """Start ``jobs`` on ``lanes`` query threads; the caller has admitted ``lanes`` slots.

        Every job gets the same lease on the current version (one request, one version).
        Each lane runs jobs one after the other until none is left; a lane's slot, and after
        the last lane the lease, are released by the pool when the lane ends or is cancelled
        before it starts, never by the request: a client that disconnects mid-query cannot
        free a slot, or close a version, that a thread still uses.

        Returns:
            (one future per lane, the outcomes: per job (True, value) or (False, exception),
            filled in when the lanes are done).
        """
        try:
            loaded = self.lease()
        except BaseException:
            self.done(lanes)
            raise
        outcomes: list[JobResult] = [(False, RuntimeError("not run"))] * len(jobs)
        order = iter(range(len(jobs)))
        left = [lanes]
        take = threading.Lock()

        def lane() -> None:
            with self._lock:
                self.running += 1
            try:
                while True:
                    with take:
                        i = next(order, None)
                    if i is None:
                        return
                    try:
                        outcomes[i] = (True, jobs[i](loaded))
                    except Exception as exc:  # handed to the request, which answers it
                        outcomes[i] = (False, exc)
            finally:
                with self._lock:
                    self.running -= 1

        def finished(_: object = None) -> None:
            with self._lock:
                self.admitted -= 1
                left[0] -= 1
                last = left[0] == 0
            if last:
                self.release(loaded)

        futures: list[Future[None]] = []
        for k in range(lanes):
            try:
                fut = self._pool.submit(lane)
            except BaseException:  # the pool is shut down: give back the lanes not started
                for _ in range(lanes - k):
                    finished()
                raise
            fut.add_done_callback(finished)
            futures.append(fut)
        return futures, outcomes

    async def run(self, jobs: Sequence[Callable[[Loaded], T]], lanes: int = 1) -> list[JobResult]:
        """:meth:`start` and wait for every job (the caller has admitted ``lanes`` slots)."""
        futures, outcomes = self.start(jobs, lanes)
        await asyncio.gather(*(asyncio.wrap_future(f) for f in futures))
        return outcomes


def run_query(
    loaded: Loaded,
    image: np.ndarray,
    prior: Prior | None,
    timing: dict[str, Any],
    executor: Executor | None = None,
    features: dict[str, Any] | None = None,
) -> tuple[HierarchyResult | None, np.ndarray | None]:
    """Extract, restrict to the prior and run the hierarchy for one decoded image
    (``features``: when given, the image's features are put in it, by method id).

    Returns:
        (the result, or None when the prior leaves no place; the allowed place ids, or None
        without a prior). With a prior the result's indices are positions in the allowed ids
        (the hierarchy ran over that sub-database); its ``matched_rows`` (a version with
        experiences: which experience matched each place) are by place id either way.
    """
    reader = loaded.reader
    t = time.perf_counter()
    per_method: dict[str, float] = {}
    feats = reader.extract_query(image, per_method, executor)
    timing["extract"] = (time.perf_counter() - t) * 1e3
    timing["extract_per_method"] = per_method
    if features is not None:
        features.update(feats)
    score_fn = place_fn = reader.scorer(feats)
    n = reader.n
    allowed: np.ndarray | None = None
    if prior is not None and loaded.has_positions:
        allowed = loaded.within(prior)
        if len(allowed) == 0:
            return None, allowed
        score_fn, n = restricted(score_fn, allowed), len(allowed)
    t = time.perf_counter()
    result = loaded.hierarchy.run(score_fn, n)
    result.matched_rows = reader.matched_rows(place_fn)
    timing["hierarchy"] = (time.perf_counter() - t) * 1e3
    return result, allowed


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim`` (None elsewhere: musl, macOS), from the symbols the process
    has loaded already (no library search)."""
    try:
        return getattr(ctypes.CDLL(None), "malloc_trim", None)
    except OSError:
        return None


_TRIM = _malloc_trim()


def _trim() -> None:
    time.sleep(0.2)  # let the thread that freed the version finish freeing it
    if _TRIM is not None:
        _TRIM(0)


def _trim_soon() -> None:
    """Give the heap a retired version freed back to the OS (called when the version is
    garbage: its CNN sessions, matrices and caches are hundreds of MB allocated by many
    threads, and glibc keeps freed pages in its arenas; without this a server's resident
    memory grew by a version's worth at each reload, see tests/service/test_reload_memory.py).
    On a thread of its own: not on a query's path."""
    threading.Thread(target=_trim, name="hmpf-trim", daemon=True).start()
