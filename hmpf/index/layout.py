"""On-disk layout of an index folder: versions, the ``CURRENT`` pointer, manifests, checksums.

::

    INDEX/
      CURRENT                 name of the version in use (switched with os.replace)
      .lock                   advisory lock held by a writer (build / add / remove / gc)
      .build/                 an interrupted or running build (resumable), never read
      .verified/<name>.json   verification stamp of a version checked in full (optional)
      v0001/                  an immutable version
        manifest.json         config + hash, methods, package versions, counts, checksums
        references.h5         names, sha256, metadata columns, global descriptors (N x D)
        local.h5              local features: ragged rows + offsets, or N x R x D blocks
        state.h5              fitted parameters per method (only when a method has any)
        thumbnails.h5         small JPEG per reference (format 1.1; hmpf.index.thumbnails)
        faiss/<method>.faiss  tier-1 FAISS index per global method
        onnx/<model>.onnx     exported CNN models the queries run (hmpf.index.models)

A version is written into ``.build/out``, every file fsynced, renamed to ``<name>``, and only
then ``CURRENT`` is replaced atomically, so an interrupted writer never changes what readers
see (``.build`` also keeps the finished images' features, for ``--resume``). ``gc`` renames a
version to ``.deleting-<name>`` before deleting it, so a killed ``gc`` leaves it whole or gone.

Integrity: the manifest lists every data file's size and sha256 (and, for files over
:data:`CHUNK_BYTES`, the sha256 of each piece, :func:`file_entry`). Whoever reads a version
checks every file against it first (:func:`check_files`; the reader does unless told not
to), so no reader serves, evaluates or copies into a new version a byte that differs from
what was written. A version is hashed whole once where it is made or checked (at publish, by
``hmpf-index verify``), which then writes its *verification stamp*,
``.verified/<name>.json`` (:func:`write_stamp`): the manifest's digest and each file's size,
mtime, ctime, inode and device. A reader that asks for it (``verify="stamp"``, the service)
skips the hashing when the stamp still matches (:func:`stamp_matches`, one ``stat`` per
file; why that is sound and what it cannot see is said there), and hashes everything
otherwise; the service then checks every byte in the background (``service.engine``). The
manifest itself carries the sha256 of its own canonical content (:data:`MANIFEST_SHA256`,
:func:`manifest_digest`), checked by :func:`read_manifest`, which every reader and
``hmpf-index verify`` go through: a field edited after the build (a method's params, the
config, the package versions) is refused like a damaged file.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import logging
import os
import platform
import re
import stat
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata
from pathlib import Path
from typing import Any, Literal

from hmpf.errors import HmpfError
from hmpf.features import file_digest

__all__ = [
    "FORMAT_VERSION",
    "VERIFIED_DIR",
    "CheckStopped",
    "FileStats",
    "VerifyMode",
    "IndexBuildError",
    "IndexCorruptError",
    "HmpfIndexError",
    "IndexLockedError",
    "IndexNotFoundError",
    "IndexVersionError",
    "OPENCV_DISTS",
    "RECORDED_PACKAGES",
    "check_files",
    "current_version",
    "file_stats",
    "file_entry",
    "file_problems",
    "fsync_dir",
    "fsync_tree",
    "installed_version",
    "is_version_name",
    "list_versions",
    "manifest_digest",
    "next_version_name",
    "package_versions",
    "read_manifest",
    "remove_stamp",
    "set_current",
    "sha256_file",
    "stamp_matches",
    "stamp_path",
    "verify_files",
    "write_json_atomic",
    "write_manifest",
    "write_stamp",
    "writer_lock",
]

log = logging.getLogger("hmpf.index")

#: Major.minor of the on-disk format. Readers accept any minor of their major (1.1 added
#: ``thumbnails.h5``, optional: a 1.0 version has none; 1.2 seals the manifest with
#: :data:`MANIFEST_SHA256`, which a 1.2 manifest must have and an older one may lack).
FORMAT_VERSION = "1.2"
#: The manifest's own checksum, one of its fields (:func:`manifest_digest`).
MANIFEST_SHA256 = "manifest_sha256"
#: The first format whose manifests carry :data:`MANIFEST_SHA256`.
_SEALED_FROM = (1, 2)
MANIFEST = "manifest.json"
CURRENT = "CURRENT"
LOCK = ".lock"
BUILD_DIR = ".build"
REFERENCES_H5 = "references.h5"
LOCAL_H5 = "local.h5"
STATE_H5 = "state.h5"
#: The places' reference profile (:func:`hmpf.index.storage.write_profile`), computed once
#: when the version is written; a version written before it existed has none.
PROFILE_H5 = "profile.h5"
FAISS_DIR = "faiss"
#: A file larger than this also gets a sha256 per piece of this size (hashed in parallel).
CHUNK_BYTES = 1 << 26
#: Prefix of a version folder being deleted by ``gc`` (renamed first, so never half a version).
DELETING = ".deleting-"
_VERSION_RE = re.compile(r"^v(\d{4,})$")
#: The two OpenCV wheels hmpf runs on (same cv2 module; either satisfies an index).
OPENCV_DISTS = ("opencv-python-headless", "opencv-contrib-python-headless")
#: Distributions whose versions a build records in the manifest (``packages``).
RECORDED_PACKAGES = (
    "hmpf",
    "numpy",
    "h5py",
    "faiss-cpu",
    *OPENCV_DISTS,
    "torch",
    "onnxruntime",
)


def installed_version(dist: str) -> str | None:
    """The installed version of a distribution, None when it is not installed."""
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def package_versions() -> dict[str, str]:
    """Python's and the installed :data:`RECORDED_PACKAGES`' versions (manifest ``packages``)."""
    out = {"python": platform.python_version()}
    for dist in RECORDED_PACKAGES:
        version = installed_version(dist)
        if version is not None:
            out[dist] = version
    return out


class HmpfIndexError(HmpfError):
    """Base of every index error."""


class IndexNotFoundError(HmpfIndexError):
    """The folder holds no index or not the requested version."""


class IndexCorruptError(HmpfIndexError):
    """A file of a version is missing, truncated, altered or inconsistent (names the file)."""


class IndexVersionError(HmpfIndexError):
    """The index was written by a format or method version this code cannot read."""


class IndexBuildError(HmpfIndexError):
    """A build, add or remove cannot proceed (bad input, disk full, unsupported option)."""


class IndexLockedError(HmpfIndexError):
    """Another writer holds the index lock."""


class CheckStopped(HmpfIndexError):
    """A check of a version's files was stopped before it finished (nothing was found)."""


sha256_file = file_digest  # sha256 hex digest of a file's bytes


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """Flush a directory entry (a rename or a new file) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_tree(root: Path) -> None:
    """fsync every file and directory under ``root`` (``root`` included)."""
    for dirpath, _, files in os.walk(root):
        for f in files:
            with open(os.path.join(dirpath, f), "rb") as fh:
                os.fsync(fh.fileno())
        fsync_dir(dirpath)


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON to ``path`` via a fsynced temporary file and :func:`os.replace`."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=1, sort_keys=False)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def is_version_name(name: str) -> bool:
    """``v0001``-style names (what ``CURRENT`` and ``hmpf-index use`` accept)."""
    return bool(_VERSION_RE.match(name))


def list_versions(root: Path) -> list[str]:
    """Published version names under ``root``, oldest first."""
    if not root.is_dir():
        return []
    names = [p.name for p in root.iterdir() if p.is_dir() and _VERSION_RE.match(p.name)]
    return sorted(names, key=lambda n: int(n[1:]))


def next_version_name(root: Path) -> str:
    """``v0001`` for an empty folder, else one more than the highest version."""
    versions = list_versions(root)
    return f"v{(int(versions[-1][1:]) + 1 if versions else 1):04d}"


def current_version(root: Path) -> str | None:
    """The version ``CURRENT`` names, or None when the folder has no published version."""
    p = root / CURRENT
    if not p.exists():
        return None
    name = p.read_text().strip()
    if not _VERSION_RE.match(name):
        raise IndexCorruptError(f"{p}: does not name a version ({name[:40]!r})")
    return name


def set_current(root: Path, version: str) -> None:
    """Point ``CURRENT`` at ``version`` atomically (temporary file + os.replace + fsync)."""
    tmp = root / f".{CURRENT}.{os.getpid()}.tmp"
    with open(tmp, "w") as fh:
        fh.write(version + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, root / CURRENT)
    fsync_dir(root)


def manifest_digest(manifest: Mapping[str, Any]) -> str:
    """sha256 of a manifest's canonical content: its JSON with sorted keys and no spaces,
    without :data:`MANIFEST_SHA256` itself (so however the file is indented, the same)."""
    body = {k: v for k, v in manifest.items() if k != MANIFEST_SHA256}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()


def write_manifest(version_dir: Path, manifest: Mapping[str, Any]) -> dict[str, Any]:
    """Write ``manifest.json`` of a version being built, sealed with :data:`MANIFEST_SHA256`.

    The caller fsyncs it with the version (:func:`fsync_tree`). Returns the manifest written
    (as :func:`read_manifest` will read it).
    """
    # As JSON reads it back (tuples as lists, keys as strings), so the digest is of that.
    sealed: dict[str, Any] = json.loads(json.dumps(dict(manifest)))
    sealed.pop(MANIFEST_SHA256, None)
    sealed[MANIFEST_SHA256] = manifest_digest(sealed)
    (version_dir / MANIFEST).write_text(json.dumps(sealed, indent=1))
    return sealed


#: Manifests already warned about (one warning per version folder and process).
_UNSEALED_WARNED: set[Path] = set()


def _check_seal(version_dir: Path, manifest: Mapping[str, Any]) -> None:
    """The manifest's own checksum: matching, or absent from an old format (a warning)."""
    p = version_dir / MANIFEST
    seal = manifest.get(MANIFEST_SHA256)
    if seal is None:
        try:
            fmt = tuple(int(x) for x in str(manifest["format_version"]).split(".")[:2])
        except ValueError:
            fmt = (0, 0)
        if fmt >= _SEALED_FROM:
            raise IndexCorruptError(
                f"{p}: format {manifest['format_version']} but no {MANIFEST_SHA256} (the "
                "manifest was edited); run `hmpf-index verify`, switch to a sound version "
                "with `hmpf-index use VERSION`, or rebuild"
            )
        if version_dir not in _UNSEALED_WARNED:
            _UNSEALED_WARNED.add(version_dir)
            log.warning(
                "%s: written before manifests had a checksum of their own (format %s): its "
                "data files are verified, an edit of the manifest itself is not detected; "
                "rebuild the index (or make a new version: hmpf-index add or remove) to get one",
                p,
                manifest["format_version"],
            )
        return
    if seal != manifest_digest(manifest):
        raise IndexCorruptError(
            f"{p}: edited after it was written (its content does not match its "
            f"{MANIFEST_SHA256}); refusing to read it: run `hmpf-index verify`, switch to a "
            "sound version with `hmpf-index use VERSION`, or rebuild"
        )


def read_manifest(version_dir: Path) -> dict[str, Any]:
    """Parse ``manifest.json`` of a version, checking the format's major version and the
    manifest's own checksum (:data:`MANIFEST_SHA256`; an old format without one: a warning).

    Raises:
        IndexCorruptError: missing, unreadable, not a manifest, or edited.
        IndexVersionError: another major format.
    """
    p = version_dir / MANIFEST
    try:
        manifest = json.loads(p.read_text())
    except FileNotFoundError:
        raise IndexCorruptError(f"{p}: missing") from None
    except (OSError, ValueError) as exc:
        raise IndexCorruptError(f"{p}: unreadable ({exc}); run `hmpf-index verify`") from None
    if not isinstance(manifest, dict) or "format_version" not in manifest:
        raise IndexCorruptError(f"{p}: not an hmpf index manifest")
    major = str(manifest["format_version"]).split(".")[0]
    if major != FORMAT_VERSION.split(".")[0]:
        raise IndexVersionError(
            f"{version_dir}: index format {manifest['format_version']}, this hmpf reads "
            f"{FORMAT_VERSION.split('.')[0]}.x; rebuild the index with this version of hmpf-index"
        )
    _check_seal(version_dir, manifest)
    return manifest


@contextlib.contextmanager
def writer_lock(root: Path) -> Iterator[None]:
    """Hold the index's exclusive writer lock (released by the OS even on kill -9)."""
    root.mkdir(parents=True, exist_ok=True)
    fh = open(root / LOCK, "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EACCES):
                raise IndexLockedError(
                    f"{root}: another hmpf-index process is writing this index; wait for it"
                ) from None
            raise
        yield
    finally:
        fh.close()


def file_entry(path: Path) -> dict[str, Any]:
    """The manifest's ``files`` entry of one file, from one read of it.

    ``{"sha256", "bytes"}``; a file over :data:`CHUNK_BYTES` also gets ``chunk_bytes`` and
    ``chunks``, the sha256 of each ``chunk_bytes`` piece in order, so that a reader can hash
    the pieces on every core (:func:`file_problems`). Matching every piece's sha256, with the
    size, is as strong as matching the whole file's: the pieces cover the file.
    """
    whole = hashlib.sha256()
    chunks = []
    with open(path, "rb") as fh:
        while block := fh.read(CHUNK_BYTES):
            whole.update(block)
            chunks.append(hashlib.sha256(block).hexdigest())
    entry: dict[str, Any] = {"sha256": whole.hexdigest(), "bytes": path.stat().st_size}
    if len(chunks) > 1:
        entry.update(chunk_bytes=CHUNK_BYTES, chunks=chunks)
    return entry


def _range_digest(path: Path, offset: int, length: int, stop: threading.Event | None = None) -> str:
    """sha256 of ``length`` bytes of ``path`` from ``offset`` (read in 1 MiB blocks).

    Raises:
        CheckStopped: ``stop`` was set (looked at before each block).
    """
    h = hashlib.sha256()
    buf = bytearray(1 << 20)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as fh:
        fh.seek(offset)
        while length > 0:
            if stop is not None and stop.is_set():
                raise CheckStopped(f"{path}: check stopped")
            got = fh.readinto(view[: min(length, len(buf))])
            if not got:
                break
            h.update(view[:got])
            length -= got
    return h.hexdigest()


def _pieces(p: Path, entry: Mapping[str, Any]) -> list[tuple[int, int, str]] | str:
    """(offset, length, sha256) of what to hash in ``p``, or a problem with the entry."""
    size = int(entry["bytes"])
    chunks = entry.get("chunks")
    if not chunks:
        return [(0, size, entry["sha256"])]
    step = int(entry.get("chunk_bytes", 0))
    if step <= 0 or len(chunks) != -(-size // step):
        return f"{p}: the manifest's chunk list does not cover the file's {size} bytes"
    return [(i * step, min(step, size - i * step), sha) for i, sha in enumerate(chunks)]


def file_problems(
    version_dir: Path,
    manifest: Mapping[str, Any],
    *,
    workers: int | None = None,
    stop: threading.Event | None = None,
) -> list[str]:
    """Every file of a version against its manifest's ``files`` (size and sha256 of each).

    Every listed file is read whole and hashed (sha256, about 2 GB/s per core with SHA
    instructions): the pieces a file's entry lists (:func:`file_entry`), or the whole file,
    on one thread per core (hashlib releases the GIL), largest first. A file that is missing,
    of another size, of another digest, or present but not listed is a problem.

    Args:
        workers: hashing threads (default: one per core); 1 hashes on the calling thread
            (the service's background check, which must not take the query cores).
        stop: when set, the check ends within one 1 MiB read (:class:`CheckStopped`).

    Returns:
        one line per problem, naming the file (empty: every file is as written).

    Raises:
        CheckStopped: ``stop`` was set before the check finished.
    """
    listed = manifest.get("files")
    if not isinstance(listed, Mapping) or not listed:
        return [f"{version_dir / MANIFEST}: lists no files, so nothing can be verified"]
    problems: list[str] = []
    todo: list[tuple[Path, int, int, str]] = []
    pieced: set[Path] = set()
    for rel, entry in sorted(listed.items()):
        p = version_dir / rel
        if not p.is_file():
            problems.append(f"{p}: missing")
        elif p.stat().st_size != entry["bytes"]:
            problems.append(f"{p}: {p.stat().st_size} bytes, manifest says {entry['bytes']}")
        else:
            pieces = _pieces(p, entry)
            if isinstance(pieces, str):
                problems.append(pieces)
            else:
                todo += [(p, *piece) for piece in pieces]
                if entry.get("chunks"):
                    pieced.add(p)
    todo.sort(key=lambda t: -t[2])
    if todo:
        threads = min(len(todo), workers or os.cpu_count() or 1)
        if threads == 1:
            digests = [_range_digest(t[0], t[1], t[2], stop) for t in todo]
        else:
            with ThreadPoolExecutor(threads) as pool:
                digests = list(pool.map(lambda t: _range_digest(t[0], t[1], t[2], stop), todo))
        bad: dict[Path, list[int]] = {}
        for (p, offset, _, want), got in zip(todo, digests, strict=True):
            if got != want:
                bad.setdefault(p, []).append(offset)
        for p, offsets in bad.items():
            where = f" from byte {min(offsets)}" if p in pieced else ""
            problems.append(f"{p}: sha256 differs from the manifest{where} (file is corrupt)")
    extra = _unlisted(version_dir, listed)
    problems += [f"{version_dir / rel}: not listed in the manifest" for rel in sorted(extra)]
    return sorted(problems)


def _unlisted(version_dir: Path, listed: Mapping[str, Any]) -> set[str]:
    """Files under ``version_dir`` (relative, POSIX) other than the manifest and those in
    ``listed``."""
    return {
        p.relative_to(version_dir).as_posix()
        for p in version_dir.rglob("*")
        if p.is_file() and p.name != MANIFEST
    } - set(listed)


def check_files(version_dir: Path, manifest: Mapping[str, Any]) -> float:
    """:func:`file_problems`, as an error: what opening a version for reading does first.

    Returns:
        the seconds the check took (logged).

    Raises:
        IndexCorruptError: naming every file that does not match, and what to do.
    """
    t = time.perf_counter()
    problems = file_problems(version_dir, manifest)
    if problems:
        raise IndexCorruptError(
            f"{version_dir.name} is corrupt, refusing to read it: {'; '.join(problems)}; "
            f"check every version with `hmpf-index verify --index {version_dir.parent}` and "
            "switch to a sound one with `hmpf-index use VERSION`, or rebuild"
        )
    seconds = time.perf_counter() - t
    total = sum(int(e["bytes"]) for e in manifest["files"].values())
    log.info(
        "%s: %d files (%.1f MB) match their sha256 (%.2f s)",
        version_dir,
        len(manifest["files"]),
        total / 1e6,
        seconds,
    )
    return seconds


# -- verification stamps -----------------------------------------------------------------------
#: Folder of the verification stamps, in the index folder beside the versions (never inside
#: one: a version folder holds only its manifest and the files the manifest lists).
VERIFIED_DIR = ".verified"
#: Per file, what a stamp records of it: ``os.stat``'s size, mtime_ns, ctime_ns, ino, dev.
FileStats = dict[str, dict[str, int]]
#: What opening a version checks (:func:`verify_files`).
VerifyMode = bool | Literal["full", "stamp"]


def stamp_path(version_dir: Path) -> Path:
    """The verification stamp of ``version_dir``: ``<index>/.verified/<version>.json``."""
    return version_dir.parent / VERIFIED_DIR / f"{version_dir.name}.json"


def file_stats(version_dir: Path, names: Iterable[str] | None = None) -> FileStats | None:
    """Each file's size, identity (inode, device) and last change (mtime, ctime, in ns), by
    its path relative to ``version_dir``.

    Args:
        names: the files (default: every file under the folder but the manifest).

    Returns:
        the stats, or None when one of the files is missing or not a regular file.
    """
    if names is None:
        names = sorted(_unlisted(version_dir, {}))
    out: FileStats = {}
    for rel in names:
        try:
            st = os.stat(version_dir / rel)
        except OSError:
            return None
        if not stat.S_ISREG(st.st_mode):
            return None
        out[rel] = {
            "size": st.st_size,
            "mtime_ns": st.st_mtime_ns,
            "ctime_ns": st.st_ctime_ns,
            "ino": st.st_ino,
            "dev": st.st_dev,
        }
    return out


def write_stamp(
    version_dir: Path, manifest: Mapping[str, Any], before: FileStats | None = None
) -> bool:
    """Record that ``version_dir``'s files were just checked whole against ``manifest``.

    Call it only once every byte has been found as the manifest lists it: after
    :func:`file_problems` found nothing, or at publish, whose sha256 were computed from these
    very files. The stamp (:func:`stamp_path`, written atomically) holds the manifest's digest
    (:func:`manifest_digest`) and each listed file's :func:`file_stats`.

    Args:
        before: the files' stats taken before that check began: the stamp is written only
            if they are unchanged, so that it never vouches for a byte written while the
            check was reading (a write changes mtime and ctime).

    Returns:
        whether a stamp was written: False when a file changed or is missing, or the index
        folder cannot be written (logged; the next load then checks every file again).
    """
    listed = manifest.get("files")
    if not isinstance(listed, Mapping) or not listed:
        return False
    now = file_stats(version_dir, sorted(listed))
    if now is None or (before is not None and any(before.get(k) != v for k, v in now.items())):
        log.warning(
            "%s: files changed while they were checked; no verification stamp written (the "
            "next load checks every file again)",
            version_dir,
        )
        return False
    stamp = {
        "version": version_dir.name,
        MANIFEST_SHA256: manifest_digest(manifest),
        "stamped_at": time.time(),
        "files": now,
    }
    path = stamp_path(version_dir)
    try:
        path.parent.mkdir(exist_ok=True)
        write_json_atomic(path, stamp)
    except OSError as exc:
        log.info(
            "%s: no verification stamp written (%s); the next load checks every file again",
            version_dir,
            exc,
        )
        return False
    return True


def stamp_matches(version_dir: Path, manifest: Mapping[str, Any]) -> bool:
    """Whether ``version_dir``'s files are, to the file system, those its stamp vouches for.

    True when the stamp names this version and this manifest (its digest), and every file
    the manifest lists has exactly the stamp's size, mtime, ctime, inode and device (and the
    manifest's size), with no unlisted file beside them. Only metadata is read (one
    ``stat`` per file): milliseconds, whatever the files' size.

    Why that is enough to skip hashing, and what it does not catch: any write to a file
    through the file system (``write``, ``truncate``, ``mmap``) sets its mtime and ctime;
    ctime is set by the kernel, to the clock, and no call sets it back (``utime`` restores
    mtime but sets ctime); a file replaced, restored from a copy or moved in from elsewhere
    is another inode. A matching stamp thus means that no byte was written through the file
    system since the full check the stamp records. What it cannot see: bytes changed below
    the file system (a failing disk, a write to the raw device), a system clock set back to
    the second a file was written, and a stamp forged by someone who may write the index
    folder (who could also rewrite the manifest). The service therefore checks a version it
    opened by its stamp in full in the background (``service.engine``), and
    ``hmpf-index verify`` checks every byte.
    """
    try:
        stamp = json.loads(stamp_path(version_dir).read_text())
    except (OSError, ValueError):
        return False
    listed = manifest.get("files")
    if not isinstance(stamp, dict) or not isinstance(listed, Mapping) or not listed:
        return False
    if stamp.get("version") != version_dir.name:
        return False
    if stamp.get(MANIFEST_SHA256) != manifest_digest(manifest):
        return False
    now = file_stats(version_dir, sorted(listed))
    if now is None or stamp.get("files") != now:
        return False
    for rel, entry in listed.items():
        if not isinstance(entry, Mapping) or now[rel]["size"] != entry.get("bytes"):
            return False
    return not _unlisted(version_dir, listed)


def remove_stamp(version_dir: Path) -> bool:
    """Delete ``version_dir``'s stamp (the version was found corrupt, or is deleted): the
    next load checks every file. Returns whether there was one to delete."""
    try:
        stamp_path(version_dir).unlink()
    except FileNotFoundError:
        return False
    except OSError as exc:
        log.warning("%s: its verification stamp cannot be deleted (%s)", version_dir, exc)
        return False
    return True


def verify_files(
    version_dir: Path, manifest: Mapping[str, Any], mode: VerifyMode = True
) -> tuple[str | None, float | None]:
    """What opening a version checks before anything is read from it, by ``mode``:

    * ``True`` or ``"full"``: every byte of every file (:func:`check_files`);
    * ``"stamp"``: nothing more when the files are those a full check stamped
      (:func:`stamp_matches`: a ``stat`` per file), else every byte, and once that passes
      a fresh stamp (:func:`write_stamp`, from the files' stats before the check);
    * ``False``: nothing (for a caller that has just checked them, ``hmpf-index verify``).

    Returns:
        (how the files were verified: ``"full"``, ``"stamp"`` or None; the seconds their
        hashing took, None when nothing was hashed).

    Raises:
        IndexCorruptError: a file does not match (from :func:`check_files`).
        ValueError: another mode.
    """
    if mode is False:
        return None, None
    if mode is True or mode == "full":
        return "full", check_files(version_dir, manifest)
    if mode != "stamp":
        raise ValueError(f"verify: True, False, 'full' or 'stamp', not {mode!r}")
    t = time.perf_counter()
    if stamp_matches(version_dir, manifest):
        log.info(
            "%s: files unchanged since their full check (verification stamp, %.3f s): not "
            "hashed again",
            version_dir,
            time.perf_counter() - t,
        )
        return "stamp", None
    listed = manifest.get("files")
    before = file_stats(version_dir, sorted(listed)) if isinstance(listed, Mapping) else None
    seconds = check_files(version_dir, manifest)
    write_stamp(version_dir, manifest, before)
    return "full", seconds
