"""``verify``, ``gc``, ``info`` and ``list``."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from hmpf.errors import HmpfError
from hmpf.index import layout
from hmpf.index.layout import IndexCorruptError
from hmpf.index.reader import IndexReader, resolve_version

__all__ = ["gc", "info", "list_versions", "verify"]


def verify(index: str | Path, version: str | None = None) -> list[str]:
    """Recompute every data file's sha256 and size, then open the version and check shapes.

    Returns:
        Problems found, one line each naming the file (empty: the version is sound).
    """
    path = resolve_version(Path(index), version)
    try:
        manifest = layout.read_manifest(path)
    except HmpfError as exc:
        return [str(exc)]
    problems = []
    listed = manifest.get("files", {})
    for rel, entry in sorted(listed.items()):
        p = path / rel
        if not p.is_file():
            problems.append(f"{p}: missing")
        elif p.stat().st_size != entry["bytes"]:
            problems.append(f"{p}: {p.stat().st_size} bytes, manifest says {entry['bytes']}")
        elif layout.sha256_file(p) != entry["sha256"]:
            problems.append(f"{p}: sha256 differs from the manifest (file is corrupt)")
    extra = {
        str(p.relative_to(path))
        for p in path.rglob("*")
        if p.is_file() and p.name != layout.MANIFEST
    } - set(listed)
    problems += [f"{path / rel}: not listed in the manifest" for rel in sorted(extra)]
    if problems:
        return problems
    try:
        with IndexReader(path.parent, path.name) as reader:
            for mid in reader.methods:
                reader.faiss_index(mid)  # loads and checks ntotal / d
    except HmpfError as exc:
        problems.append(str(exc))
    return problems


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

    Also deletes an abandoned ``.build`` folder. Returns the deleted paths.
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
        if not dry_run:
            for p in paths:
                shutil.rmtree(p)
            layout.fsync_dir(root)
    return [str(p) for p in paths]
