"""``verify``, ``use``, ``gc``, ``info`` and ``list``."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any

from hmpf.errors import HmpfError
from hmpf.index import layout
from hmpf.index.layout import IndexCorruptError, IndexNotFoundError
from hmpf.index.reader import IndexReader, resolve_version

__all__ = [
    "STALE_TMP_MAX_AGE_S",
    "STALE_TMP_MIN_AGE_S",
    "gc",
    "info",
    "stale_temporary_files",
    "list_versions",
    "stale_stamps",
    "use",
    "verify",
    "verify_all",
]

#: A writer's temporary file in the index folder younger than this is never deleted.
STALE_TMP_MIN_AGE_S = 60.0
#: One older than this is deleted even if a process with its pid runs.
STALE_TMP_MAX_AGE_S = 24 * 3600.0
#: The temporary files writers make in the index folder itself, named after their process:
#: ``.CURRENT.<pid>.tmp`` (:func:`hmpf.index.layout.set_current`) and
#: ``.sequence-key.<pid>.<hex>.tmp`` (the service's sequence key, :mod:`service.track`).
_WRITER_TMP = re.compile(r"^\.(?:CURRENT|sequence-key)\.(\d{1,10})(?:\.[0-9a-f]+)?\.tmp$")


def verify(index: str | Path, version: str | None = None) -> list[str]:
    """Recompute every data file's sha256 and size, then open the version and check shapes.

    A sound version gets a fresh verification stamp (:func:`hmpf.index.layout.write_stamp`,
    from the files' stats before they were hashed: a server then opens it without hashing
    it again); a corrupt one loses its stamp, so that every reader hashes it in full (and
    refuses it).

    Returns:
        Problems found, one line each naming the file (empty: the version is sound).
    """
    path = resolve_version(Path(index), version)
    try:
        manifest = layout.read_manifest(path)
    except HmpfError as exc:
        layout.remove_stamp(path)
        return [str(exc)]
    listed = manifest.get("files")
    before = layout.file_stats(path, sorted(listed)) if isinstance(listed, dict) else None
    problems = layout.file_problems(path, manifest)
    if not problems:
        try:
            with IndexReader(path.parent, path.name, verify=False) as reader:  # just verified
                for mid in reader.methods:
                    reader.faiss_index(mid)  # loads and checks ntotal / d
        except HmpfError as exc:
            problems.append(str(exc))
    if problems:
        layout.remove_stamp(path)
    else:
        layout.write_stamp(path, manifest, before)
    return problems


def verify_all(index: str | Path) -> dict[str, list[str]]:
    """:func:`verify` every published version (and that ``CURRENT`` names one of them).

    Returns:
        version name -> its problems (empty: sound), oldest first; a bad ``CURRENT`` is
        reported under the key ``"CURRENT"``.

    Raises:
        IndexNotFoundError: the folder holds no published version.
    """
    root = Path(index)
    versions = layout.list_versions(root)
    if not versions:
        resolve_version(root)  # the folder or its versions are missing: a clear error
    out = {v: verify(root, v) for v in versions}
    try:
        current = layout.current_version(root)
    except HmpfError as exc:
        return out | {"CURRENT": [str(exc)]}
    if current is None or current not in versions:
        out["CURRENT"] = [f"{root / layout.CURRENT}: names {current!r}, not a published version"]
    return out


def use(index: str | Path, version: str) -> tuple[str | None, str]:
    """Point ``CURRENT`` at ``version`` after verifying it (as :func:`verify`), atomically.

    Holds the writer lock, so no ``gc`` deletes the version meanwhile.

    Returns:
        (the version ``CURRENT`` named before, or None; ``version``).

    Raises:
        IndexNotFoundError: no such version. IndexCorruptError: it does not verify
            (``CURRENT`` is left as it was).
    """
    root = Path(index)
    if not layout.is_version_name(version):
        raise IndexNotFoundError(f"{version!r} is not a version name (like v0002)")
    with layout.writer_lock(root):
        resolve_version(root, version)
        problems = verify(root, version)
        if problems:
            raise IndexCorruptError(
                f"{version} is corrupt, CURRENT left as it was: {'; '.join(problems)}"
            )
        try:
            old = layout.current_version(root)
        except IndexCorruptError:
            old = None
        layout.set_current(root, version)
    return old, version


def list_versions(index: str | Path) -> list[dict[str, Any]]:
    """Every published version with its operation, count and date, oldest first."""
    root = Path(index)
    current = layout.current_version(root)
    out = []
    for name in layout.list_versions(root):
        entry: dict[str, Any] = {"version": name, "current": name == current}
        try:
            m = layout.read_manifest(root / name)
            entry.update(
                operation=m.get("operation"),
                images=m.get("images", {}).get("count"),
                created=m.get("created"),
                config=m.get("config", {}).get("name"),
                bytes=m.get("summary", {}).get("bytes_total"),
            )
        except HmpfError as exc:
            entry["error"] = str(exc)
        out.append(entry)
    return out


def info(index: str | Path, version: str | None = None) -> dict[str, Any]:
    """The manifest of a version (default: current), without the per-file list."""
    path = resolve_version(Path(index), version)
    manifest = layout.read_manifest(path)
    return {k: v for k, v in manifest.items() if k != "files"} | {
        "files": {k: v["bytes"] for k, v in manifest.get("files", {}).items()}
    }


def gc(index: str | Path, keep: int = 0, dry_run: bool = False) -> list[str]:
    """Delete old versions (never the current one; also keep the ``keep`` newest others).

    Also deletes an abandoned ``.build`` folder, and the temporary files a killed writer left
    in the index folder (:func:`stale_temporary_files`: e.g. ``.CURRENT.<pid>.tmp`` of a
    process killed between the fsync and the replace of ``CURRENT``). Each folder is first
    renamed out of the way (``.deleting-<name>``, atomic, fsynced) and only then deleted, so
    a ``gc`` killed midway leaves every version whole or gone; the next ``gc`` deletes what
    it left.

    A deleted version's verification stamp (``.verified/<name>.json``) goes first, and so do
    stamps of versions no longer there (:func:`stale_stamps`); neither is in the list returned.

    Returns:
        the deleted paths (their names before the rename).
    """
    root = Path(index)
    with layout.writer_lock(root):
        current = layout.current_version(root)
        if current is None:
            raise IndexCorruptError(f"{root}: no CURRENT version; refusing to delete anything")
        others = [v for v in layout.list_versions(root) if v != current]
        doomed = others[: max(0, len(others) - keep)]
        paths = [root / v for v in doomed]
        if (root / layout.BUILD_DIR).exists():
            paths.append(root / layout.BUILD_DIR)
        leftovers = sorted(root.glob(layout.DELETING + "*"))
        stale = stale_temporary_files(root)
        if not dry_run:
            for v in doomed:
                layout.remove_stamp(root / v)  # first: a version never outlives its stamp
            for p in leftovers:
                shutil.rmtree(p)
            for p in paths:
                shutil.rmtree(_move_away(p))
            for p in stale_stamps(root):
                p.unlink(missing_ok=True)
            for p in stale:
                p.unlink(missing_ok=True)
            layout.fsync_dir(root)
    return [str(p) for p in paths + leftovers + stale]


def stale_stamps(root: Path, now: float | None = None) -> list[Path]:
    """Files of ``.verified`` that vouch for nothing: the stamp of a version that is not (or
    no longer) published, and a stamp's temporary file older than
    :data:`STALE_TMP_MIN_AGE_S` (a stamp is written in milliseconds; deleting a live
    writer's temporary file only makes its stamp fail to appear, which is safe: the version
    is then hashed in full when opened)."""
    folder = root / layout.VERIFIED_DIR
    if not folder.is_dir():
        return []
    now = time.time() if now is None else now
    versions = set(layout.list_versions(root))
    out = []
    for p in sorted(folder.iterdir()):
        if p.suffix == ".json" and not p.name.startswith("."):
            if p.stem not in versions:
                out.append(p)
        elif p.name.endswith(".tmp") and p.is_file():
            with contextlib.suppress(FileNotFoundError):
                if now - p.stat().st_mtime > STALE_TMP_MIN_AGE_S:
                    out.append(p)
    return out


def stale_temporary_files(root: Path, now: float | None = None) -> list[Path]:
    """The writers' temporary files in ``root`` that no live writer can still hold.

    ``.CURRENT.<pid>.tmp`` and ``.sequence-key.<pid>.<hex>.tmp`` live for the milliseconds of
    one write and fsync; a writer killed before its rename leaves one behind. Such a file is
    stale when it is older than :data:`STALE_TMP_MIN_AGE_S` and no process with its pid runs
    here, or older than :data:`STALE_TMP_MAX_AGE_S` whatever runs. Why this is sound:

    * ``CURRENT`` is switched only under the writer lock, which ``gc`` holds: no
      ``.CURRENT`` file can be in use while it runs, whatever its pid says. The rules still
      hold for a writer that does not take the lock (and for the service's key file, made
      without it): deleting a live writer's file makes its rename fail (nothing is changed,
      it reports an error), never half a file published.
    * The minimum age covers a writer in another container on the same folder, whose pid
      this process cannot see (it looks dead); the maximum age covers a dead writer's pid
      since reused by another process (it looks alive).
    """
    now = time.time() if now is None else now
    out = []
    for p in sorted(root.iterdir()) if root.is_dir() else []:
        m = _WRITER_TMP.match(p.name)
        if m is None or not p.is_file():
            continue
        try:
            age = now - p.stat().st_mtime
        except FileNotFoundError:
            continue  # its writer finished meanwhile
        if age > STALE_TMP_MAX_AGE_S or (age > STALE_TMP_MIN_AGE_S and not _running(int(m[1]))):
            out.append(p)
    return out


def _running(pid: int) -> bool:
    """Whether a process with this pid runs (and is visible) here."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except OverflowError:
        return False
    return True


def _move_away(path: Path) -> Path:
    """Rename ``path`` to ``.deleting-<name>`` beside it (atomic; fsynced)."""
    trash = path.with_name(layout.DELETING + path.name)
    path.rename(trash)
    layout.fsync_dir(path.parent)
    return trash
