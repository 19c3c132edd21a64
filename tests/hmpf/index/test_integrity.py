"""Index integrity (issue 23): nothing is read, served or copied from a version whose files
do not match the checksums of its manifest. On real small indexes (synthetic images, real
HDF5 files), damaged by flipping one byte inside a dataset's data, where the HDF5 library
cannot notice it and answers change:

* the reader (so ``hmpf-serve`` at start and on reload, and ``hmpf-eval --index``) refuses a
  corrupt version: start exits 2 with the reason, reload is a 409 that keeps the old version;
* ``add`` and ``remove`` refuse to derive a version from a corrupt parent;
* ``hmpf-index verify`` checks every version by default;
* ``gc`` moves a version out of the way before deleting it, so a crash leaves it whole or
  gone, and the next ``gc`` finishes the job;
* ``hmpf-index use VERSION`` switches ``CURRENT`` to a verified version, atomically.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient

import indexer.maintenance
from hmpf.index import IndexCorruptError, IndexNotFoundError, IndexReader, layout
from indexer.build import BuildOptions, add, build, remove
from indexer.cli import main as index_main
from service.app import create_app
from service.auth import add_key
from service.cli import main as serve_main
from service.settings import load_settings
from tests.conftest import SMALL_INDEX_CONFIG, synthetic_image, write_synthetic_images

CONFIG = SMALL_INDEX_CONFIG
OPTS = BuildOptions(workers=1, progress=False)


def _flip(path: Path, dataset: str, row: int = 0) -> None:
    """Flip one byte inside ``dataset``'s data (row ``row``): the HDF5 structure stays
    valid, so only the checksums can tell."""
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        if isinstance(ds, h5py.Group):  # local arrays: ragged rows or equal-count blocks
            ds = ds["data" if "data" in ds else "blocks"]
        offset = ds.id.get_offset()
        assert offset is not None and ds.chunks is None
        row_bytes = int(np.prod(ds.shape[1:], dtype=np.int64)) * ds.dtype.itemsize
    with open(path, "r+b") as fh:
        fh.seek(offset + row * row_bytes + 1)
        byte = fh.read(1)
        fh.seek(offset + row * row_bytes + 1)
        fh.write(bytes([byte[0] ^ 0x40]))


def _cli(*args: object) -> int:
    return index_main([str(a) for a in args])


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An index with two versions: v0001 (6 images) and v0002 (+3, current)."""
    base = tmp_path_factory.mktemp("integrity")
    config = base / "config.yaml"
    config.write_text(CONFIG)
    index = base / "index"
    build(config, write_synthetic_images(base / "a", 6), index, options=OPTS)
    add(index, write_synthetic_images(base / "b", 3, seed=50, prefix="new"), options=OPTS)
    return index


@pytest.fixture
def index(clean: Path, tmp_path: Path) -> Path:
    """A fresh copy of :func:`clean` that a test may damage."""
    return Path(shutil.copytree(clean, tmp_path / "index"))


def _keys(tmp_path: Path) -> tuple[str, dict[str, str]]:
    path = tmp_path / "keys.yaml"
    return str(path), {
        "vehicle": add_key(path, "car", "vehicle"),
        "admin": add_key(path, "ops", "admin"),
    }


# -- verify on load -------------------------------------------------------------------------------
def test_reader_refuses_a_flipped_byte_in_the_global_matrix(index: Path) -> None:
    with IndexReader(index) as r:
        before = r.global_matrix("gist")[0].copy()
    _flip(index / "v0002" / layout.REFERENCES_H5, "global/gist")
    with pytest.raises(IndexCorruptError, match=r"v0002/references\.h5: sha256 differs"):
        IndexReader(index)
    with IndexReader(index, verify=False) as r:  # the damage is inside the data
        assert not np.array_equal(r.global_matrix("gist")[0], before)


def test_reader_refuses_a_flipped_byte_in_local_features(index: Path) -> None:
    _flip(index / "v0002" / layout.LOCAL_H5, "local/kaze/descriptors", row=3)
    with pytest.raises(IndexCorruptError, match=r"v0002/local\.h5: sha256 differs"):
        IndexReader(index)
    with IndexReader(index, "v0001") as r:  # other versions are not affected
        assert r.n == 6


def test_serve_refuses_to_start_on_a_corrupt_version(
    index: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    _flip(index / "v0002" / layout.REFERENCES_H5, "global/hog")
    monkeypatch.setenv("HMPF_AUTH", "false")
    # an unusable address: had the index loaded, uvicorn would fail to bind (not exit 2)
    assert serve_main(["--index", str(index), "--host", "203.0.113.1", "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert "hmpf-serve: error:" in err and "references.h5: sha256 differs" in err
    assert "Traceback" not in err


def test_reload_refuses_a_corrupt_version_and_keeps_the_old_one(
    index: Path, tmp_path: Path
) -> None:
    keys_file, keys = _keys(tmp_path)
    layout.set_current(index, "v0001")
    settings = load_settings(None, index=index, keys_file=keys_file, workers=1, queue=4)
    image = cv2.imencode(".png", cv2.cvtColor(synthetic_image(3), cv2.COLOR_RGB2BGR))[1]

    def ask(c: TestClient) -> dict:
        r = c.post(
            "/v1/localize",
            files={"image": ("q.png", image.tobytes(), "image/png")},
            headers={"X-API-Key": keys["vehicle"]},
        )
        assert r.status_code == 200, r.text
        return dict(r.json())

    with TestClient(create_app(settings)) as c:
        first = ask(c)
        assert first["index_version"] == "v0001"
        _flip(index / "v0002" / layout.LOCAL_H5, "local/kaze/descriptors")
        layout.set_current(index, "v0002")
        r = c.post("/v1/index/reload", headers={"X-API-Key": keys["admin"]})
        assert r.status_code == 409, r.text
        error = r.json()["error"]
        assert error["code"] == "index_unusable"
        assert "kept version v0001" in error["message"]
        assert "local.h5: sha256 differs" in error["message"]
        again = ask(c)
        assert again["index_version"] == "v0001" and again["match"] == first["match"]


# -- derived versions -----------------------------------------------------------------------------
def test_remove_and_add_refuse_a_corrupt_parent(
    index: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _flip(index / "v0002" / layout.REFERENCES_H5, "global/gist", row=4)
    with pytest.raises(IndexCorruptError, match="references.h5: sha256 differs"):
        remove(index, ["img000.png"])
    with pytest.raises(IndexCorruptError, match="references.h5: sha256 differs"):
        add(index, write_synthetic_images(tmp_path / "c", 2, seed=80, prefix="more"), options=OPTS)
    assert _cli("remove", "--index", index, "img001.png") == 2
    assert "sha256 differs" in capsys.readouterr().err
    assert layout.list_versions(index) == ["v0001", "v0002"]
    assert layout.current_version(index) == "v0002"


# -- verify ---------------------------------------------------------------------------------------
def test_verify_checks_every_version_by_default(index: Path, capsys: pytest.CaptureFixture) -> None:
    assert _cli("verify", "--index", index) == 0
    out = capsys.readouterr().out
    assert "v0001" in out and "v0002" in out
    _flip(index / "v0001" / layout.LOCAL_H5, "local/kaze/descriptors")  # not the current one
    assert _cli("verify", "--index", index) == 1
    corrupt = [line for line in capsys.readouterr().out.splitlines() if "CORRUPT" in line]
    assert corrupt and all("v0001/local.h5: sha256 differs" in line for line in corrupt)
    assert _cli("verify", "--index", index, "--index-version", "v0002") == 0
    assert capsys.readouterr().out.strip() == "ok"


# -- gc -------------------------------------------------------------------------------------------
def test_gc_killed_midway_leaves_no_half_deleted_version(
    index: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_rmtree = shutil.rmtree

    def crash(path: str | Path, *args: object, **kwargs: object) -> None:
        """Delete the manifest first, then die, as a kill in the middle of a deletion."""
        (Path(path) / layout.MANIFEST).unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(indexer.maintenance.shutil, "rmtree", crash)
    with pytest.raises(KeyboardInterrupt):
        indexer.maintenance.gc(index)
    monkeypatch.setattr(indexer.maintenance.shutil, "rmtree", real_rmtree)
    # v0001 is gone as a whole: no version folder without its manifest
    assert layout.list_versions(index) == ["v0002"]
    assert indexer.maintenance.verify_all(index) == {"v0002": []}
    # the next gc removes what the killed one left
    indexer.maintenance.gc(index)
    assert {p.name for p in index.iterdir()} == {
        layout.CURRENT,
        layout.LOCK,
        layout.VERIFIED_DIR,
        "v0002",
    }
    # and the stamp of the version it deleted
    assert [p.name for p in (index / layout.VERIFIED_DIR).iterdir()] == ["v0002.json"]


# -- use ------------------------------------------------------------------------------------------
def test_use_switches_current_to_a_verified_version(
    index: Path, capsys: pytest.CaptureFixture
) -> None:
    assert _cli("use", "--index", index, "v0001") == 0
    assert layout.current_version(index) == "v0001"
    assert "v0002 -> v0001" in capsys.readouterr().out
    with IndexReader(index) as r:
        assert r.version == "v0001" and r.n == 6
    _flip(index / "v0002" / layout.REFERENCES_H5, "global/hog")
    assert _cli("use", "--index", index, "v0002") == 2
    assert "references.h5: sha256 differs" in capsys.readouterr().err
    assert layout.current_version(index) == "v0001"
    assert _cli("use", "--index", index, "v0009") == 2
    assert "no version 'v0009'" in capsys.readouterr().err
    assert layout.current_version(index) == "v0001"
    with pytest.raises(IndexNotFoundError):
        indexer.maintenance.use(index, "v0009")


# -- the pieces' checksums ------------------------------------------------------------------------
def test_large_files_are_verified_piece_by_piece_as_strongly_as_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file over ``CHUNK_BYTES`` lists a sha256 per piece (hashed on every core): the pieces
    are the file's consecutive slices, and a flipped byte in any piece is found."""
    monkeypatch.setattr(layout, "CHUNK_BYTES", 4096)
    config = tmp_path / "config.yaml"
    config.write_text(CONFIG)
    index = tmp_path / "index"
    build(config, write_synthetic_images(tmp_path / "a", 4), index, options=OPTS)
    version = index / "v0001"
    entry = layout.read_manifest(version)["files"][layout.LOCAL_H5]
    data = (version / layout.LOCAL_H5).read_bytes()
    assert entry["chunk_bytes"] == 4096 and len(entry["chunks"]) == -(-len(data) // 4096) > 2
    assert entry["chunks"] == [
        hashlib.sha256(data[a : a + 4096]).hexdigest() for a in range(0, len(data), 4096)
    ]
    assert entry["sha256"] == hashlib.sha256(data).hexdigest()
    with IndexReader(index) as r:
        assert r.n == 4
    for at in (0, len(data) // 2, len(data) - 1):  # first, middle and last (short) piece
        damaged = bytearray(data)
        damaged[at] ^= 0x01
        (version / layout.LOCAL_H5).write_bytes(bytes(damaged))
        with pytest.raises(IndexCorruptError, match=f"from byte {at // 4096 * 4096} "):
            IndexReader(index)
    (version / layout.LOCAL_H5).write_bytes(data)
    manifest = json.loads((version / layout.MANIFEST).read_text())
    manifest["files"][layout.LOCAL_H5]["chunks"].pop()  # a list that does not cover the file
    layout.write_manifest(version, manifest)  # sealed: the chunk list itself is checked
    with pytest.raises(IndexCorruptError, match="chunk list does not cover"):
        IndexReader(index)
