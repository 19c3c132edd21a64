"""On-disk layout of an index folder: versions, the ``CURRENT`` pointer, manifests, checksums.

::

    INDEX/
      CURRENT                 name of the version in use (switched with os.replace)
      .lock                   advisory lock held by a writer (build / add / remove / gc)
      .build/                 an interrupted or running build (resumable), never read
      v0001/                  an immutable version
        manifest.json         config + hash, methods, package versions, counts, checksums
        references.h5         names, sha256, metadata columns, global descriptors (N x D)
        local.h5              local features: ragged rows + offsets, or N x R x D blocks
        state.h5              fitted parameters per method (only when a method has any)
        faiss/<method>.faiss  tier-1 FAISS index per global method

A version is written into ``.build/out``, every file fsynced, renamed to ``<name>``, and only
then ``CURRENT`` is replaced atomically, so an interrupted writer never changes what readers
see (``.build`` also keeps the finished images' features, for ``--resume``).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import platform
import re
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

from hmpf.errors import HmpfError
from hmpf.features import file_digest

__all__ = [
    "FORMAT_VERSION",
    "IndexBuildError",
    "IndexCorruptError",
    "HmpfIndexError",
    "IndexLockedError",
    "IndexNotFoundError",
    "IndexVersionError",
    "OPENCV_DISTS",
    "RECORDED_PACKAGES",
    "current_version",
    "fsync_dir",
    "fsync_tree",
    "installed_version",
    "list_versions",
    "next_version_name",
    "package_versions",
    "read_manifest",
    "set_current",
    "sha256_file",
    "write_json_atomic",
    "writer_lock",
]

#: Major.minor of the on-disk format. Readers accept any minor of their major.
FORMAT_VERSION = "1.0"
MANIFEST = "manifest.json"
CURRENT = "CURRENT"
LOCK = ".lock"
BUILD_DIR = ".build"
REFERENCES_H5 = "references.h5"
LOCAL_H5 = "local.h5"
STATE_H5 = "state.h5"
FAISS_DIR = "faiss"
_VERSION_RE = re.compile(r"^v(\d{4,})$")
#: The two OpenCV wheels hmpf runs on (same cv2 module; either satisfies an index).
OPENCV_DISTS = ("opencv-python-headless", "opencv-contrib-python-headless")
#: Distributions whose versions a build records in the manifest (``packages``).
RECORDED_PACKAGES = ("hmpf", "numpy", "h5py", "faiss-cpu", *OPENCV_DISTS, "torch")


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


def read_manifest(version_dir: Path) -> dict[str, Any]:
    """Parse ``manifest.json`` of a version, checking the format's major version."""
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
