"""Verification stamps: a version hashed in full once (at publish, by ``hmpf-index verify``)
opens without hashing again while its files are, to the file system, those that were
checked; any change to a file, its replacement by a copy, or another manifest sends the
reader back to the full check, which refuses a corrupt file.

Real indexes on synthetic images, the real ``hmpf-index`` command line.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
from pathlib import Path

import pytest

from hmpf.index import IndexCorruptError, IndexReader, layout
from indexer import maintenance
from indexer.build import BuildOptions, remove
from indexer.cli import main as index_main

OPTS = BuildOptions(workers=1, progress=False)


def _largest(version: Path) -> Path:
    listed = layout.read_manifest(version)["files"]
    return version / max(listed, key=lambda rel: listed[rel]["bytes"])


def _flip_last_byte(path: Path) -> None:
    """Change one byte, the size unchanged (a write: mtime and ctime move)."""
    raw = bytearray(path.read_bytes())
    raw[-1] ^= 0xFF
    path.write_bytes(bytes(raw))


def test_publish_stamps_the_version_outside_its_folder(index: Path) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    stamp = layout.stamp_path(version)
    assert stamp == index / ".verified" / "v0001.json" and stamp.is_file()
    body = json.loads(stamp.read_text())
    assert body["manifest_sha256"] == layout.manifest_digest(manifest)
    assert set(body["files"]) == set(manifest["files"])
    for entry in body["files"].values():
        assert set(entry) == {"size", "mtime_ns", "ctime_ns", "ino", "dev"}
    # the version folder holds its manifest and what it lists, nothing else
    inside = {p.relative_to(version).as_posix() for p in version.rglob("*") if p.is_file()}
    assert inside == set(manifest["files"]) | {layout.MANIFEST}
    assert layout.stamp_matches(version, manifest)
    assert layout.file_problems(version, manifest) == []


def test_a_stamped_version_opens_without_hashing(index: Path) -> None:
    with IndexReader(index, verify="stamp") as reader:
        assert (reader.verified_by, reader.verify_seconds) == ("stamp", None)
    with IndexReader(index) as reader:  # the default still hashes everything
        assert reader.verified_by == "full" and reader.verify_seconds is not None
    with IndexReader(index, verify="full") as reader:
        assert reader.verified_by == "full" and reader.verify_seconds is not None
    with IndexReader(index, verify=False) as reader:
        assert (reader.verified_by, reader.verify_seconds) == (None, None)


def test_a_changed_file_falls_back_to_the_full_check_and_is_refused(index: Path) -> None:
    version = index / "v0001"
    data = _largest(version)
    before = data.stat()
    _flip_last_byte(data)
    # even with its mtime set back, ctime says it was written
    os.utime(data, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert data.stat().st_size == before.st_size
    assert data.stat().st_mtime_ns == before.st_mtime_ns
    assert not layout.stamp_matches(version, layout.read_manifest(version))
    with pytest.raises(IndexCorruptError, match=f"{data.name}: sha256 differs"):
        IndexReader(index, verify="stamp")


def test_a_replaced_file_of_the_same_bytes_is_hashed_again_then_stamped(index: Path) -> None:
    """A copy put in place (same bytes, same mtime) is another inode: the full check runs,
    passes, and writes a fresh stamp that the next open trusts."""
    version = index / "v0001"
    data = _largest(version)
    copy = data.with_name("copy.tmp")
    shutil.copy2(data, copy)
    os.replace(copy, data)
    manifest = layout.read_manifest(version)
    assert not layout.stamp_matches(version, manifest)
    with IndexReader(index, verify="stamp") as reader:
        assert reader.verified_by == "full" and reader.verify_seconds is not None
    assert layout.stamp_matches(version, manifest)
    with IndexReader(index, verify="stamp") as reader:
        assert reader.verified_by == "stamp"


def test_a_stamp_of_another_manifest_or_an_extra_file_does_not_match(index: Path) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    stamp = layout.stamp_path(version)
    body = json.loads(stamp.read_text())
    stamp.write_text(json.dumps(body | {"manifest_sha256": "0" * 64}))
    assert not layout.stamp_matches(version, manifest)
    stamp.write_text(json.dumps(body))
    assert layout.stamp_matches(version, manifest)
    stamp.write_text("{not json")
    assert not layout.stamp_matches(version, manifest)
    stamp.write_text(json.dumps(body))
    (version / "stray.bin").write_bytes(b"x")
    assert not layout.stamp_matches(version, manifest)


def test_no_stamp_is_written_when_a_file_changed_during_the_check(index: Path) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    layout.remove_stamp(version)
    before = layout.file_stats(version, sorted(manifest["files"]))
    assert before is not None
    _flip_last_byte(_largest(version))  # as if written while the check was reading
    assert not layout.write_stamp(version, manifest, before)
    assert not layout.stamp_path(version).exists()


def test_only_stamp_mode_writes_a_stamp(index: Path) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    layout.remove_stamp(version)
    assert layout.verify_files(version, manifest, True)[0] == "full"
    assert layout.verify_files(version, manifest, False) == (None, None)
    assert not layout.stamp_path(version).exists()
    assert layout.verify_files(version, manifest, "stamp")[0] == "full"
    assert layout.verify_files(version, manifest, "stamp") == ("stamp", None)
    with pytest.raises(ValueError):
        layout.verify_files(version, manifest, "sometimes")  # type: ignore[arg-type]


def test_verify_stamps_a_sound_version_and_unstamps_a_corrupt_one(
    index: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    layout.remove_stamp(version)
    assert index_main(["verify", "--index", str(index)]) == 0
    assert layout.stamp_matches(version, manifest)
    layout.remove_stamp(version)
    assert maintenance.verify(index, "v0001") == []
    assert layout.stamp_matches(version, manifest)
    _flip_last_byte(_largest(version))
    capsys.readouterr()
    assert index_main(["verify", "--index", str(index)]) == 1
    assert "CORRUPT v0001" in capsys.readouterr().out
    assert not layout.stamp_path(version).exists()


def test_gc_removes_the_stamps_of_the_versions_it_deletes(index: Path) -> None:
    remove(index, ["img000.png"], options=OPTS)  # publishes v0002
    stamps = index / layout.VERIFIED_DIR
    assert sorted(p.name for p in stamps.iterdir()) == ["v0001.json", "v0002.json"]
    orphan = stamps / "v0009.json"  # a stamp of a version long gone
    orphan.write_text("{}")
    assert maintenance.gc(index, dry_run=True) == [str(index / "v0001")]
    assert orphan.exists() and (stamps / "v0001.json").exists()
    assert maintenance.gc(index) == [str(index / "v0001")]
    assert sorted(p.name for p in stamps.iterdir()) == ["v0002.json"]
    assert layout.stamp_matches(index / "v0002", layout.read_manifest(index / "v0002"))


def test_the_full_check_on_one_thread_finds_the_same_and_can_be_stopped(index: Path) -> None:
    version = index / "v0001"
    manifest = layout.read_manifest(version)
    assert layout.file_problems(version, manifest, workers=1) == []
    _flip_last_byte(_largest(version))
    assert layout.file_problems(version, manifest, workers=1) == layout.file_problems(
        version, manifest
    )
    assert layout.file_problems(version, manifest, workers=1)  # and it is a problem
    stop = threading.Event()
    stop.set()
    with pytest.raises(layout.CheckStopped):
        layout.file_problems(version, manifest, workers=1, stop=stop)
