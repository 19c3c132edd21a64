"""Index hardening (issue 36, item 7): ``gc`` removes what a killed writer left of ``CURRENT``'s
switch, and an edited manifest is detected by ``verify`` and by every reader.

Real indexes on synthetic images, real processes (one killed with SIGKILL between the fsync
and the replace of ``CURRENT``), the real ``hmpf-index`` command line.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from hmpf.index import IndexReader, layout
from indexer import maintenance
from indexer.build import BuildOptions
from indexer.cli import main as index_main

OPTS = BuildOptions(workers=1, progress=False)
ROOT = Path(__file__).resolve().parents[2]


def _killed_between_fsync_and_replace(root: Path, version: str) -> Path:
    """Run :func:`layout.set_current` in a process that is killed (SIGKILL) right after the
    fsync of the temporary file, before its replace: what it leaves behind."""
    script = textwrap.dedent(
        f"""
        import os, signal
        from pathlib import Path
        from hmpf.index import IndexReader, layout
        os.replace = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)
        layout.set_current(Path({str(root)!r}), {version!r})
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=False)
    assert proc.returncode == -signal.SIGKILL
    (left,) = root.glob(".CURRENT.*.tmp")
    return left


def _age(path: Path, seconds: float) -> None:
    then = time.time() - seconds
    os.utime(path, (then, then))


def test_gc_removes_the_temporary_current_a_killed_writer_left(
    index: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    left = _killed_between_fsync_and_replace(index, "v0001")
    assert layout.current_version(index) == "v0001"  # CURRENT itself is whole
    _age(left, 2 * maintenance.STALE_TMP_MIN_AGE_S)
    assert index_main(["gc", "--index", str(index), "--dry-run"]) == 0
    assert f"would delete {left}" in capsys.readouterr().out and left.exists()
    assert index_main(["gc", "--index", str(index)]) == 0
    assert f"deleted {left}" in capsys.readouterr().out
    assert not left.exists() and layout.current_version(index) == "v0001"
    assert maintenance.verify_all(index) == {"v0001": []}


def test_gc_keeps_a_temporary_file_a_live_writer_may_still_hold(index: Path) -> None:
    """Kept: a fresh one (its writer may run in another container, whose pids are not seen
    here) and one of a running process; removed: a dead process's once old enough, and any
    once older than any write takes (its pid may have been reused)."""
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        dead_pid = 2**22 + 1  # beyond the kernel's largest pid_max: never a running process
        fresh_dead = index / f".CURRENT.{dead_pid}.tmp"
        old_live = index / f".CURRENT.{live.pid}.tmp"
        ancient_live = index / f".sequence-key.{live.pid}.0a1b2c3d.tmp"
        old_dead_key = index / f".sequence-key.{dead_pid}.deadbeef.tmp"
        unrelated = index / ".CURRENT.notapid.tmp"
        for p in (fresh_dead, old_live, ancient_live, old_dead_key, unrelated):
            p.write_text("v0001\n")
        _age(old_live, 2 * maintenance.STALE_TMP_MIN_AGE_S)
        _age(ancient_live, 2 * maintenance.STALE_TMP_MAX_AGE_S)
        _age(old_dead_key, 2 * maintenance.STALE_TMP_MIN_AGE_S)
        _age(unrelated, 2 * maintenance.STALE_TMP_MAX_AGE_S)
        deleted = maintenance.gc(index)
        assert sorted(deleted) == sorted(map(str, (ancient_live, old_dead_key)))
        assert fresh_dead.exists() and old_live.exists() and unrelated.exists()
    finally:
        live.kill()
        live.wait()


# -- the manifest's own checksum -----------------------------------------------------------------
def _edit(version: Path, change: Any) -> None:
    """Edit ``manifest.json`` as a person with an editor would (the JSON rewritten as is)."""
    path = version / layout.MANIFEST
    manifest = json.loads(path.read_text())
    change(manifest)
    path.write_text(json.dumps(manifest, indent=1))


def _a_methods_params(manifest: dict[str, Any]) -> None:
    entry = manifest["methods"]["kaze"]
    entry["params"] = {**entry.get("params", {}), "max_keypoints": 4000}


def test_an_edited_manifest_is_detected_by_verify_and_by_readers(
    index: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    assert manifest["manifest_sha256"] == layout.manifest_digest(manifest)
    assert manifest["format_version"] == layout.FORMAT_VERSION
    assert maintenance.verify(index) == []
    original = (version / layout.MANIFEST).read_bytes()
    for change in (
        _a_methods_params,
        lambda m: m["config"].__setitem__("name", "renamed"),
        lambda m: m["packages"].__setitem__("numpy", "0.1"),
        lambda m: m.__setitem__("operation", "build "),
    ):
        (version / layout.MANIFEST).write_bytes(original)
        _edit(version, change)
        (problem,) = maintenance.verify(index)
        assert "manifest.json" in problem and "edited" in problem, problem
        with pytest.raises(layout.IndexCorruptError, match="edited"):
            IndexReader(index)
        assert index_main(["verify", "--index", str(index)]) != 0
        assert "edited" in capsys.readouterr().out + capsys.readouterr().err
    # the checksum taken out of a current-format manifest: not an old index, refused too
    (version / layout.MANIFEST).write_bytes(original)
    _edit(version, lambda m: m.pop("manifest_sha256"))
    with pytest.raises(layout.IndexCorruptError, match="manifest_sha256"):
        IndexReader(index)
    # a manifest written (sealed) by hmpf itself is sound again
    manifest = json.loads(original)
    layout.write_manifest(version, manifest)
    assert maintenance.verify(index) == []
    IndexReader(index).close()


def test_an_index_from_before_manifest_checksums_is_read_with_a_warning(
    index: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A 1.1 manifest had no checksum: read as before, with a warning naming the fix."""
    version = index / "v0001"
    _edit(version, lambda m: (m.pop("manifest_sha256"), m.update(format_version="1.1")))
    with caplog.at_level("WARNING", "hmpf.index"):
        assert maintenance.verify(index) == []
        with IndexReader(index) as reader:
            assert reader.n == 3
    assert "checksum of their own" in caplog.text and "rebuild" in caplog.text
