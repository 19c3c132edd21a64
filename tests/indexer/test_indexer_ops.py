"""hmpf-index operations on synthetic images: build, add, remove, verify, info, list, gc,
bad input (each rejected before any work), skipped images, fitted state, approximate FAISS."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
from typing import ClassVar

import cv2
import h5py
import numpy as np
import pytest

import hmpf.features
import indexer.build
import indexer.inputs
from hmpf.config import parse_config
from hmpf.errors import DatasetError, ImageError
from hmpf.imageio import load_image
from hmpf.index import IndexBuildError, IndexReader
from hmpf.methods import GlobalMethod, MethodConfig, register
from hmpf.methods.base import MetricSpec, euclidean
from indexer.build import BuildOptions, add, build, remove
from indexer.cli import main
from tests.conftest import SMALL_INDEX_CONFIG, synthetic_image, write_synthetic_images

CONFIG = SMALL_INDEX_CONFIG
OPTS = BuildOptions(workers=1, progress=False)
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def config_file(tmp_path: Path) -> Path:
    p = tmp_path / "config.yaml"
    p.write_text(CONFIG)
    return p


def _datasets(version: Path) -> dict[str, np.ndarray]:
    out = {}
    for name in ("references.h5", "local.h5"):
        with h5py.File(version / name) as f:
            f.visititems(
                lambda k, o, name=name: (
                    out.__setitem__(f"{name}:{k}", o[()]) if isinstance(o, h5py.Dataset) else None
                )
            )
    return out


def _cli(*args: object) -> int:
    return main([str(a) for a in args])


def test_build_add_remove_list_gc(tmp_path, config_file, capsys):
    a = write_synthetic_images(tmp_path / "a", 6)
    b = write_synthetic_images(tmp_path / "b", 3, seed=50, prefix="new")
    index = tmp_path / "index"
    assert (
        _cli(
            "build",
            "--config",
            config_file,
            "--images",
            a,
            "--index",
            index,
            "--workers",
            1,
            "--quiet",
        )
        == 0
    )
    assert "published v0001 with 6 references" in capsys.readouterr().out
    s = add(index, b, options=OPTS)
    assert (s.version, s.images, s.extracted, s.reused) == ("v0002", 9, 3, 6)
    # add == a clean build of the union
    union = write_synthetic_images(tmp_path / "union", 6)
    write_synthetic_images(union, 3, seed=50, prefix="new")
    clean = tmp_path / "clean"
    build(config_file, union, clean, options=OPTS)
    got, want = _datasets(index / "v0002"), _datasets(clean / "v0001")
    assert set(got) == set(want)
    for k in want:
        if not k.endswith("sources") and not k.endswith("source_id"):
            assert np.array_equal(got[k], want[k]), k
    s = remove(index, ["img001.png", "new002.png"])
    with IndexReader(index) as r:
        assert r.version == "v0003" and r.n == 7
        assert "img001.png" not in r.refs.names
        res = r.hierarchy().run(r.scorer(r.extract_query(synthetic_image(3))), r.n)
        assert r.refs.names[res.match] == "img003.png"
    capsys.readouterr()
    assert _cli("list", "--index", index) == 0
    listing = capsys.readouterr().out
    assert "* v0003" in listing and "v0001" in listing
    assert _cli("info", "--index", index, "--json") == 0
    assert json.loads(capsys.readouterr().out)["images"]["count"] == 7
    assert _cli("info", "--index", index, "--index-version", "v0001", "--json") == 0
    assert json.loads(capsys.readouterr().out)["images"]["count"] == 6
    assert _cli("verify", "--index", index, "--index-version", "v0002") == 0
    assert capsys.readouterr().out.strip() == "ok"
    assert _cli("gc", "--index", index, "--keep", 1) == 0
    assert sorted(p.name for p in index.glob("v*")) == ["v0002", "v0003"]
    assert (index / "CURRENT").read_text().strip() == "v0003"


def test_version_flag_and_index_version_do_not_collide(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("hmpf-index (hmpf ")
    with pytest.raises(SystemExit) as exc:  # the old spelling is gone, not silently reused
        main(["info", "--index", str(tmp_path), "--version", "v0001"])
    assert exc.value.code == 2
    assert "--version NAME is now --index-version NAME" in capsys.readouterr().err


def test_verify_names_the_corrupt_file(tmp_path, config_file, capsys):
    index = tmp_path / "index"
    build(config_file, write_synthetic_images(tmp_path / "a", 4), index, options=OPTS)
    assert _cli("verify", "--index", index) == 0
    f = index / "v0001" / "local.h5"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f.write_bytes(bytes(data))
    capsys.readouterr()
    assert _cli("verify", "--index", index) == 1
    out = capsys.readouterr().out
    assert "local.h5: sha256 differs" in out and "references.h5" not in out


def test_metadata_is_stored(tmp_path, config_file):
    a = write_synthetic_images(tmp_path / "a", 3)
    csv = tmp_path / "meta.csv"
    csv.write_text(
        "name,lat,lon,timestamp,sequence\n"
        "img000.png,-27.47,153.02,2020-01-01T00:00:00+00:00,run1\n"
        "img002.png,-27.48,153.03,1577836900,run1\n"
    )
    build(config_file, a, tmp_path / "index", metadata=csv, options=OPTS)
    with IndexReader(tmp_path / "index") as r:
        assert r.refs.meta["lat"][0] == -27.47 and np.isnan(r.refs.meta["lat"][1])
        assert r.refs.meta["timestamp"][0] == 1577836800.0
        assert list(r.refs.meta["sequence"]) == ["run1", "", "run1"]


@pytest.mark.parametrize(
    ("csv_text", "match"),
    [
        ("file,lat\nimg000.png,1\n", "'name' column"),
        ("name,latitude\nimg000.png,1\n", "unknown column"),
        ("name,lat\nimg000.png,1\nghost.png,2\n", "name no image.*ghost.png"),
        ("name,lat\nimg000.png,north\n", "not a number"),
        ("name,lat\nimg000.png,1\nimg000.png,2\n", "duplicate row"),
    ],
)
def test_bad_metadata_rejected_before_work(tmp_path, config_file, csv_text, match):
    a = write_synthetic_images(tmp_path / "a", 2)
    csv = tmp_path / "meta.csv"
    csv.write_text(csv_text)
    with pytest.raises(DatasetError, match=match):
        build(config_file, a, tmp_path / "index", metadata=csv, options=OPTS)
    assert not (tmp_path / "index").exists()


def test_bad_folder_and_config_rejected_before_work(tmp_path, config_file, capsys):
    (tmp_path / "empty").mkdir()
    index = tmp_path / "index"
    with pytest.raises(DatasetError, match="holds no image"):
        build(config_file, tmp_path / "empty", index, options=OPTS)
    dup = write_synthetic_images(tmp_path / "dup", 1)
    (dup / "IMG000.PNG").write_bytes((dup / "img000.png").read_bytes())
    with pytest.raises(DatasetError, match="duplicate image names"):
        build(config_file, dup, index, options=OPTS)
    bad = tmp_path / "bad.yaml"
    bad.write_text("tiers:\n  - {methods: [hog, nosuch], k: 1}\n")
    assert _cli("build", "--config", bad, "--images", dup, "--index", index) == 2
    assert "unknown method 'nosuch'" in capsys.readouterr().err
    with pytest.raises(IndexBuildError, match="not a tier-1 global method"):
        build(config_file, dup, index, options=BuildOptions(faiss={"kaze": "HNSW32"}))
    assert not index.exists()


def test_unreadable_image_skipped_or_strict(tmp_path, config_file):
    a = write_synthetic_images(tmp_path / "a", 3)
    (a / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    s = build(config_file, a, tmp_path / "index", options=OPTS)
    assert s.images == 3 and [x["name"] for x in s.skipped] == ["broken.jpg"]
    manifest = json.loads((tmp_path / "index" / "v0001" / "manifest.json").read_text())
    assert manifest["summary"]["skipped"][0]["name"] == "broken.jpg"
    with pytest.raises(IndexBuildError, match="broken.jpg.*--strict"):
        build(config_file, a, tmp_path / "i2", options=BuildOptions(workers=1, strict=True))
    assert not (tmp_path / "i2" / "CURRENT").exists()


def _broken_images(folder: Path) -> dict[str, str]:
    """Three kinds of unreadable file next to readable ones; name -> load_image's reason."""
    good = cv2.imencode(".jpg", synthetic_image(7))[1].tobytes()
    (folder / "b_garbage.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    (folder / "c_truncated.jpg").write_bytes(good[: len(good) // 2])
    (folder / "d_empty.png").write_bytes(b"")
    cv2.imwrite(str(folder / "e_one_pixel.png"), np.zeros((1, 1, 3), np.uint8))
    cv2.imwrite(str(folder / "f_tiny_ok.png"), np.full((2, 3, 3), 200, np.uint8))
    reasons = {}
    for p in sorted(folder.iterdir()):
        try:
            load_image(p)
        except ImageError as exc:
            reasons[p.name] = exc.reason
    assert len(reasons) == 4
    return reasons


def test_unreadable_images_found_up_front_with_load_image_reasons(tmp_path):
    folder = write_synthetic_images(tmp_path / "a", 2)
    reasons = _broken_images(folder)
    bad = indexer.inputs.check_images(sorted(folder.iterdir())).unreadable
    assert {p.name: exc.reason for p, exc in bad.items()} == reasons
    assert all(str(p) == exc.source for p, exc in bad.items())


def test_check_images_reads_each_file_once_for_digest_and_probe(tmp_path, monkeypatch):
    """One read per file gives both the digest (hmpf.features.file_digest's) and the
    verdict; a file that cannot be read gets the old "unreadable:<OS error>" digest and
    load_image's reason."""
    folder = write_synthetic_images(tmp_path / "a", 2)
    reasons = _broken_images(folder)
    paths = [*sorted(folder.iterdir()), folder / "gone.png"]
    reads: list[str] = []
    real_read = Path.read_bytes

    def counting(self):
        reads.append(self.name)
        return real_read(self)

    monkeypatch.setattr(Path, "read_bytes", counting)
    check = indexer.inputs.check_images(paths)
    monkeypatch.setattr(Path, "read_bytes", real_read)
    assert sorted(reads) == sorted([p.name for p in paths] + ["gone.png"])  # + load_image's
    assert check.digests[:-1] == [hmpf.features.file_digest(p) for p in paths[:-1]]
    assert check.digests[-1] == f"unreadable:{os.strerror(errno.ENOENT)}"
    got = {p.name: exc.reason for p, exc in check.unreadable.items()}
    assert got == {**reasons, "gone.png": "no such file"}
    assert list(got) == [p.name for p in paths if p.name in got]  # in order
    assert all(str(p) == exc.source for p, exc in check.unreadable.items())


def test_unreadable_images_skipped_in_one_extraction_pass(tmp_path, config_file, monkeypatch):
    """The unreadable images are found before extraction: one pass over the readable ones
    (not one restarted pass per unreadable image), and --strict names every one."""
    folder = write_synthetic_images(tmp_path / "a", 3)
    reasons = _broken_images(folder)
    calls = []
    real = indexer.build.extract_images

    def counting(paths, *args, **kwargs):
        calls.append([Path(p).name for p in paths])
        return real(paths, *args, **kwargs)

    monkeypatch.setattr(indexer.build, "extract_images", counting)
    s = build(config_file, folder, tmp_path / "index", options=OPTS)
    assert s.skipped == [{"name": n, "reason": r} for n, r in reasons.items()]
    assert calls == [["f_tiny_ok.png", "img000.png", "img001.png", "img002.png"]]
    assert s.images == 4 and s.resumed == 0
    with pytest.raises(IndexBuildError) as exc:
        build(config_file, folder, tmp_path / "i2", options=BuildOptions(workers=1, strict=True))
    assert all(name in str(exc.value) for name in reasons)
    assert "rerun without --strict to skip these 4" in str(exc.value)
    assert len(calls) == 1 and not (tmp_path / "i2" / ".build").exists()


def test_image_failing_after_the_check_is_an_error_naming_it(tmp_path, config_file, monkeypatch):
    folder = write_synthetic_images(tmp_path / "a", 2)
    (folder / "late.jpg").write_bytes(b"\xff\xd8 broken only after the check")
    monkeypatch.setattr(indexer.inputs, "probe_image", lambda data, source="<bytes>": None)
    with pytest.raises(IndexBuildError, match="late.jpg.*passed the check before extraction"):
        build(config_file, folder, tmp_path / "index", options=OPTS)
    assert not (tmp_path / "index" / "CURRENT").exists()


def test_add_rejects_known_names(tmp_path, config_file):
    a = write_synthetic_images(tmp_path / "a", 2)
    build(config_file, a, tmp_path / "index", options=OPTS)
    with pytest.raises(IndexBuildError, match="already in the index"):
        add(tmp_path / "index", a, options=OPTS)


class ToyConfig(MethodConfig):
    dim: int = 4


@register
class ToyFit(GlobalMethod):
    """A global method with a fitted mean (stands in for VLAD centroids / PCA)."""

    name = "toyfit_index_test"
    Config: ClassVar[type[MethodConfig]] = ToyConfig
    dim = 4

    def __init__(self, config: MethodConfig | None = None) -> None:
        super().__init__(config)
        self.mean: np.ndarray | None = None

    def requires_fit(self) -> bool:
        return True

    def state_arrays(self) -> dict[str, np.ndarray]:
        return {} if self.mean is None else {"mean": self.mean}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        self.mean = np.asarray(arrays["mean"], np.float32)

    def _extract(self, image: np.ndarray) -> np.ndarray:
        v = image.reshape(-1, 3).mean(0).astype(np.float32)
        return np.append(v, 1.0).astype(np.float32) - self.mean

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    def faiss_metric(self) -> MetricSpec:
        return MetricSpec("l2", 1.0)


def test_fitted_state_persists(tmp_path, monkeypatch):
    calls = []

    def fake_fit(methods, paths, **_):
        calls.append(len(paths))
        for m in methods.values():
            m.mean = np.full(4, float(len(paths)), np.float32)
        return list(methods)

    monkeypatch.setattr(hmpf.features, "fit_methods", fake_fit)
    cfg = parse_config({"tiers": [{"methods": ["toyfit_index_test", "gist"], "k": 1}]})
    a = write_synthetic_images(tmp_path / "a", 3)
    build(cfg, a, tmp_path / "index", options=OPTS)
    with IndexReader(tmp_path / "index") as r:
        assert np.array_equal(r.methods["toyfit_index_test"].mean, np.full(4, 3.0))
        assert r.manifest["methods"]["toyfit_index_test"]["state_sha256"]
    add(
        tmp_path / "index",
        write_synthetic_images(tmp_path / "b", 2, seed=9, prefix="b"),
        options=OPTS,
    )
    with IndexReader(tmp_path / "index") as r:  # kept as they are without --refit
        assert np.array_equal(r.methods["toyfit_index_test"].mean, np.full(4, 3.0))
    assert calls == [3]
    add(
        tmp_path / "index",
        write_synthetic_images(tmp_path / "c", 1, seed=20, prefix="c"),
        options=OPTS,
        refit=True,
    )
    with IndexReader(tmp_path / "index") as r:
        assert np.array_equal(r.methods["toyfit_index_test"].mean, np.full(4, 6.0))
        feat = r.methods["toyfit_index_test"].extract(synthetic_image(0))
        assert np.allclose(r.global_matrix("toyfit_index_test")[0], feat)


def test_approximate_faiss_small_map_equals_exact(tmp_path, config_file):
    a = write_synthetic_images(tmp_path / "a", 12)
    build(config_file, a, tmp_path / "exact", options=OPTS)
    opts = BuildOptions(
        workers=1, progress=False, faiss={"*": "IVF2,Flat"}, faiss_params={"*": "nprobe=1"}
    )
    build(config_file, a, tmp_path / "approx", options=opts)
    with IndexReader(tmp_path / "exact") as e, IndexReader(tmp_path / "approx") as x:
        assert not x.is_exact("gist") and e.is_exact("gist")
        q = e.extract_query(synthetic_image(5))
        # every reference is in the exact sample of a small map: same answer as exact
        re_, rx = e.hierarchy().run(e.scorer(q), e.n), x.hierarchy().run(x.scorer(q), x.n)
        assert re_.match == rx.match == 5
        ids, _ = x.search("gist", q["gist"], 3)
        assert ids[0] == 5


def test_faiss_factory_from_config_and_flag_override(tmp_path, config_file):
    a = write_synthetic_images(tmp_path / "a", 8)
    cfg = tmp_path / "ivf.yaml"
    cfg.write_text(
        config_file.read_text() + '\nindex:\n  faiss: {"*": "IVF2,Flat"}\n'
        "  faiss_params: {'*': nprobe=2}\n"
    )
    build(cfg, a, tmp_path / "from_config", options=OPTS)
    with IndexReader(tmp_path / "from_config") as r:
        assert not r.is_exact("gist")
        assert r.manifest["methods"]["gist"]["faiss"]["factory"] == "IVF2,Flat"
    flag = BuildOptions(workers=1, progress=False, faiss={"gist": "Flat"})
    build(cfg, a, tmp_path / "overridden", options=flag)
    with IndexReader(tmp_path / "overridden") as r:
        assert r.is_exact("gist")


def test_faiss_params_flag_for_all_and_for_one_method(tmp_path, config_file):
    """``--faiss-params nprobe=1`` (the help's own form) applies to every tier-1 method;
    ``gist=nprobe=2`` to gist only. It used to be read as a method named ``nprobe``."""
    index = tmp_path / "index"
    a = write_synthetic_images(tmp_path / "a", 12)
    args = ["build", "--config", config_file, "--images", a, "--index", index, "--workers", 1]
    args += ["--quiet", "--faiss", "IVF2,Flat", "--faiss-params", "nprobe=1"]
    args += ["--faiss-params", "gist=nprobe=2"]
    assert _cli(*args) == 0
    with IndexReader(index) as r:
        assert r.faiss_info("hog")["params"] == "nprobe=1"  # type: ignore[index]
        assert r.faiss_info("gist")["params"] == "nprobe=2"  # type: ignore[index]
