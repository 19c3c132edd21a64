"""The places' reference profile, computed once when a version is written (``profile.h5``)
and read at load, on real indexes of Gardens Point day_right (two routes, one ordered by
time, a route-augmented tier-1 method): the stored profile equals, bit for bit, the one a
reader builds from the version's descriptors, after build, add, remove and an experience
merge; a version written before versions stored it still loads and gets it built; a stored
profile of another size, of other methods, or unreadable is refused; one built with other
parameters is built anew."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import hmpf.index.reader
from hmpf.confidence import ReferenceProfile, profile_params
from hmpf.config import parse_config
from hmpf.experience_log import Record
from hmpf.index import IndexCorruptError, IndexReader, layout
from hmpf.index.storage import read_profile, write_profile
from hmpf.sequence import RouteMap
from indexer.build import BuildOptions, add, build, remove
from indexer.experiences import merge
from indexer.maintenance import verify

N_PLACES = 16
CONFIG = parse_config(
    {
        "name": "stored-profile-test",
        "methods": {"gist": {"dba": 1}},  # the profile is of the augmented (searched) matrix
        "tiers": [{"methods": ["hog", "gist"], "k": 5}, {"methods": ["gist", "sad"], "k": 1}],
    }
)
OPTS = BuildOptions(workers=1, progress=False)


def _images(gardens_point: Path, dest: Path, lo: int, hi: int) -> Path:
    dest.mkdir()
    for p in sorted((gardens_point / "day_right").iterdir())[lo:hi]:
        (dest / p.name).symlink_to(p)
    return dest


def _metadata(images: Path, csv: Path) -> Path:
    """Two routes: the first half in file order, the second ordered by (reversed) time."""
    names = sorted(p.name for p in images.iterdir())
    half = len(names) // 2
    rows = ["name,sequence,timestamp"] + [
        f"{n},a,{i}" if i < half else f"{n},b,{1000 - i}" for i, n in enumerate(names)
    ]
    csv.write_text("\n".join(rows) + "\n")
    return csv


@pytest.fixture(scope="module")
def gp_index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An index of the first 16 day_right images with two routes (v0001), built once."""
    base = tmp_path_factory.mktemp("stored_profile")
    images = _images(gardens_point, base / "refs", 0, N_PLACES)
    build(
        CONFIG, images, base / "index", metadata=_metadata(images, base / "meta.csv"), options=OPTS
    )
    return base / "index"


@pytest.fixture
def index(gp_index: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "index"
    shutil.copytree(gp_index, dst, ignore=shutil.ignore_patterns(".lock"))
    return dst


def built_at_load(r: IndexReader) -> ReferenceProfile:
    """The profile as a reader built it at every load before versions stored it: tier 1's
    global methods over the places' searched (augmented) rows, on the places' routes."""
    tier1 = [m for m in r.config.tiers[0].methods if r.methods[m].kind == "global"]
    db = {m: np.asarray(r.global_matrix(m))[: r.n] for m in tier1}
    meta = r.refs.meta

    def col(name: str) -> np.ndarray | None:
        return None if name not in meta else meta[name][: r.n]

    routes = RouteMap.from_metadata(
        r.n,
        sequence=col("sequence"),
        timestamp=col("timestamp"),
        lat=col("lat"),
        lon=col("lon"),
        junction_m=r.config.sequence_params().junction_m,
    )
    return ReferenceProfile.build(r.methods, db, tier1, routes)


def assert_same(got: ReferenceProfile, want: ReferenceProfile) -> None:
    assert got.methods == want.methods and got.sign == want.sign
    assert got.mean.dtype == want.mean.dtype == np.float64
    assert np.array_equal(got.mean, want.mean, equal_nan=True)
    assert np.array_equal(got.std, want.std, equal_nan=True)


def stored(r: IndexReader) -> ReferenceProfile:
    entry = r.manifest["profile"]
    assert entry["file"] == layout.PROFILE_H5 and layout.PROFILE_H5 in r.manifest["files"]
    assert entry["methods"] == ["hog", "gist"] and entry["params"] == profile_params()
    assert entry["seconds"] >= 0
    return read_profile(r.path / layout.PROFILE_H5)


@pytest.fixture
def no_build_at_load(monkeypatch: pytest.MonkeyPatch) -> None:
    """A reader that would build the profile fails: it must read the stored one."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the reader built the profile instead of reading it")

    monkeypatch.setattr(hmpf.index.reader, "places_profile", refuse)


def _reseal(version: Path, manifest: dict) -> None:
    """Rewrite ``version``'s manifest as hmpf writes it (sealed, every file's entry fresh)."""
    manifest["files"] = {
        name: layout.file_entry(version / name)
        for name in manifest["files"]
        if (version / name).exists()
    }
    layout.write_manifest(version, manifest)


# -- round trip ----------------------------------------------------------------------------------
def test_profile_arrays_and_file_round_trip_bit_for_bit(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    mean = rng.standard_normal((2, 7))
    mean[1, 3] = np.nan  # a reference without unrelated ones: NaN, kept as NaN
    prof = ReferenceProfile(("a", "b"), (1.0, -1.0), mean, np.abs(rng.standard_normal((2, 7))))
    assert_same(ReferenceProfile.from_arrays(prof.methods, prof.to_arrays()), prof)
    write_profile(tmp_path / "p.h5", prof, {"sample": 256, "window": 2, "seed": 0})
    assert_same(read_profile(tmp_path / "p.h5"), prof)
    empty = ReferenceProfile((), (), np.zeros((0, 5)), np.zeros((0, 5)))  # no global method
    write_profile(tmp_path / "e.h5", empty, {})
    back = read_profile(tmp_path / "e.h5")
    assert back.methods == () and back.n == 5
    with pytest.raises(Exception, match="must both be"):
        ReferenceProfile.from_arrays(["a"], {"sign": np.ones(1), "mean": mean[:1], "std": mean})


# -- every published version stores its profile -----------------------------------------------
def test_built_version_stores_the_profile_a_reader_would_build(
    index: Path, no_build_at_load: None
) -> None:
    with IndexReader(index) as r:
        assert (r.path / layout.PROFILE_H5).is_file()
        want = built_at_load(r)
        assert_same(stored(r), want)
        assert_same(r.reference_profile(), want)  # read, not built (no_build_at_load)
        assert r.route_map().n_routes == 2 and want.n == N_PLACES
        # what is stored is the augmented matrix's profile, not the stored descriptors'
        raw = {m: np.asarray(r.columns(m))[: r.n] for m in ("hog", "gist")}
        plain = ReferenceProfile.build(r.methods, raw, ["hog", "gist"], r.route_map())
        assert not np.array_equal(plain.mean[1], want.mean[1])
    assert verify(index) == []


def test_add_and_remove_store_the_new_versions_profile(
    index: Path, gardens_point: Path, tmp_path: Path, no_build_at_load: None
) -> None:
    images = _images(gardens_point, tmp_path / "more", N_PLACES, N_PLACES + 4)
    add(index, images, metadata=_metadata(images, tmp_path / "more.csv"), options=OPTS)
    with IndexReader(index) as r:
        assert r.version == "v0002" and r.n == N_PLACES + 4
        assert_same(stored(r), built_at_load(r))
        names = [r.refs.names[1], r.refs.names[N_PLACES + 1]]
    remove(index, names)
    with IndexReader(index) as r:
        assert r.version == "v0003" and r.n == N_PLACES + 2
        want = built_at_load(r)
        assert_same(stored(r), want)
        assert_same(r.reference_profile(), want)


def test_experience_merge_stores_the_places_profile(
    index: Path, gardens_point: Path, no_build_at_load: None
) -> None:
    def frame(place: int, seq: int) -> Record:
        name = f"Image{place:03d}.jpg"
        return Record(
            image=(gardens_point / "night_right" / name).read_bytes(),
            content_type="image/jpeg",
            place=place,
            place_name=name,
            index_version="v0001",
            p_correct=0.99,
            vehicle="car1",
            timestamp=1.7e9 + seq,
            mode="sequence",
            log="c" * 32,
            seq=seq,
        )

    report = merge(index, [frame(p, i) for i, p in enumerate((2, 3, 9))], gates=False, options=OPTS)
    assert report.added == 3
    with IndexReader(index) as r:
        assert r.has_experiences and r.n == N_PLACES and r.n_rows == N_PLACES + 3
        want = built_at_load(r)  # the places' rows only: experiences are not profiled
        assert_same(stored(r), want)
        assert_same(r.reference_profile(), want)


# -- versions written before, and damaged ones ---------------------------------------------------
def _without_profile(version: Path) -> None:
    """Make ``version`` what a build before stored profiles wrote."""
    manifest = json.loads((version / layout.MANIFEST).read_text())
    (version / layout.PROFILE_H5).unlink()
    del manifest["profile"]
    _reseal(version, manifest)


def test_version_without_a_stored_profile_loads_and_builds_it(index: Path) -> None:
    with IndexReader(index) as r:
        want = stored(r)
    _without_profile(index / "v0001")
    assert verify(index) == []
    with IndexReader(index) as r:
        assert "profile" not in r.manifest
        got = r.reference_profile()
        assert got is r.reference_profile()  # built once per reader
    assert_same(got, want)


def test_profile_built_with_other_parameters_is_built_anew(index: Path) -> None:
    version = index / "v0001"
    manifest = json.loads((version / layout.MANIFEST).read_text())
    manifest["profile"]["params"] = {**profile_params(), "version": 0}
    _reseal(version, manifest)
    with IndexReader(index) as r:
        assert_same(r.reference_profile(), built_at_load(r))


@pytest.mark.parametrize("damage", ["short", "methods", "garbage", "unlisted"])
def test_stored_profile_that_does_not_fit_is_refused(index: Path, damage: str) -> None:
    version = index / "v0001"
    path = version / layout.PROFILE_H5
    manifest = json.loads((version / layout.MANIFEST).read_text())
    prof = read_profile(path)
    if damage == "short":  # one place fewer than the version's
        write_profile(path, prof.subset(np.arange(prof.n - 1)), profile_params())
    elif damage == "methods":
        other = ReferenceProfile(("hog",), prof.sign[:1], prof.mean[:1], prof.std[:1])
        write_profile(path, other, profile_params())
    elif damage == "garbage":
        path.write_bytes(b"not hdf5" * 100)
    else:  # the entry names a file the checksums do not cover
        manifest["profile"]["file"] = "elsewhere.h5"
    _reseal(version, manifest)  # the checksums vouch for it: the reader's own check refuses
    with IndexReader(index) as r:
        with pytest.raises(IndexCorruptError, match=r"profile\.h5|elsewhere\.h5") as exc:
            r.reference_profile()
    assert "hmpf-index verify" in str(exc.value)
