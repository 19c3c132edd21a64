"""Shared fixtures. Real datasets come from ``$HMPF_DATASETS`` (default ``../shared/datasets``).

With ``HMPF_REQUIRE_DATASETS=1`` (set by ``.ci/run``) a missing dataset folder is an error
instead of skipped tests, so CI cannot pass without running the real-data tests.
"""

from __future__ import annotations

import os
import signal
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest

from hmpf import runtime
from hmpf.datasets import dataset_root

#: Fixtures that read ``$HMPF_DATASETS`` (directly or through another fixture: pytest's
#: ``item.fixturenames`` is the closure, so ``service_index`` is covered by ``gardens_point``).
#: ``gp_subset`` (test_index_reader.py) reads the data without the ``gardens_point`` fixture.
DATASET_FIXTURES = frozenset({"gardens_point", "nordland", "gp_subset"})


#: The files that take longest (30 s to 2 min each on two cores), longest first: they run
#: first, so that under pytest-xdist (``make test``: two processes, a file's tests in one) no
#: long file starts last and runs on alone at the end.
LONG_FILES = (
    "tests/e2e/test_e2e_gardens_point.py",
    "tests/e2e/test_calibration_gardens_point.py",
    "tests/indexer/test_ray_build.py",
    "tests/hmpf/evaluation/test_calibrate.py",
    "tests/service/test_ray_shards.py",
    "tests/hmpf/evaluation/test_sequence_eval.py",
    "tests/hmpf/methods/test_cnn_runtime.py",
    "tests/hmpf/evaluation/test_experiments.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark every test that uses a dataset fixture ``dataset``, so ``pytest -m "not dataset"``
    is an offline suite (tests that read the data without a fixture carry the mark themselves:
    tests/hmpf/methods/test_methods.py, tests/e2e/test_e2e_gardens_point.py). Then move the
    tests of :data:`LONG_FILES` to the front, in that order (the rest keep theirs)."""
    for item in items:
        if DATASET_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.dataset)
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
    # pytest-xdist sends tests to its workers by id: of tests sharing one, it runs one
    counts = Counter(item.nodeid for item in items)
    same = sorted(nodeid for nodeid, n in counts.items() if n > 1)
    if same:
        raise pytest.UsageError(f"tests with the same id (give each its own): {same[:5]}")


#: Set to 1 in each pytest-xdist worker (unless set already): the workers share the cores, and
#: thread pools on more threads than the worker's share spin and wait (the whole suite on 2
#: cores: 658 s, 987 s of CPU without; 548 s, 778 s of CPU with; the session note of
#: 2026-11-28).
WORKER_THREADS = ("HMPF_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def pytest_configure(config: pytest.Config) -> None:
    """In a pytest-xdist worker: one compute thread per process (:data:`WORKER_THREADS`, read
    by hmpf, by torch when imported and by the commands the tests start; BLAS already
    loaded is limited through threadpoolctl)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    for name in WORKER_THREADS:
        os.environ.setdefault(name, "1")
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # the service extra's; without it BLAS keeps its threads
        return
    threadpool_limits(1)


def pytest_sessionstart(session: pytest.Session) -> None:
    if os.environ.get("HMPF_REQUIRE_DATASETS") == "1":
        gp = dataset_root() / "gardens_point"
        if not gp.is_dir():
            raise pytest.UsageError(f"HMPF_REQUIRE_DATASETS=1 but {gp} does not exist")


@pytest.fixture(scope="session")
def gardens_point() -> Path:
    root = dataset_root() / "gardens_point"
    if not (root / "day_right").is_dir():
        pytest.skip(f"Gardens Point not found under {root}")
    return root


def link_route(src: Path, dst: Path, n: int) -> dict[str, Path]:
    """Symlink the first ``n`` images of Gardens Point's day_right and night_right under
    ``dst`` (a short route for quick end-to-end runs); returns traverse -> folder."""
    return {trav: link_frames(src / trav, dst / trav, n) for trav in ("day_right", "night_right")}


def link_frames(src: Path, dst: Path, n: int, start: int = 0) -> Path:
    """Symlink images ``start .. start + n - 1`` of the folder ``src`` into the new folder
    ``dst``; returns ``dst``."""
    from hmpf.datasets import list_images

    dst.mkdir()
    for p in list_images(src)[start : start + n]:
        (dst / p.name).symlink_to(p)
    return dst


@pytest.fixture(scope="session")
def gp_feature_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One feature cache (``--cache-dir``) for the tests that extract Gardens Point images, as
    a user's runs share one: an entry is keyed by the method (code version, parameters,
    fitted state, runtime) and the image's bytes, so a test reads only what the same methods
    made of the same images and extracts the rest. The cache's own tests (reuse,
    invalidation, a cached feature equal to a fresh one) are in
    tests/hmpf/evaluation/test_evaluate.py; a test that needs a cold cache keeps its own.

    Under pytest-xdist (``make test`` runs two processes) the workers share it: it sits beside
    their own temporary folders, and an entry is written to a temporary name and renamed."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = tmp_path_factory.getbasetemp().parent / "gp-feature-cache"
        shared.mkdir(exist_ok=True)
        return shared
    return tmp_path_factory.mktemp("gp-feature-cache")


@pytest.fixture(scope="session")
def nordland() -> Path:
    root = dataset_root() / "nordland_64x32"
    if not (root / "summer").is_dir():
        pytest.skip(f"Nordland thumbnails not found under {root}")
    return root


#: A small handcrafted hierarchy for index operation tests (builds in a second on synthetic
#: images; KAZE capped so local features stay small).
SMALL_INDEX_CONFIG = """
name: small-index-test
methods:
  kaze: {max_keypoints: 40}
tiers:
  - {methods: [hog, gist], k: 4}
  - {methods: [sad, kaze], k: 1}
"""


def synthetic_image(seed: int, size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """A textured RGB uint8 image (blobs and edges) that KAZE and HOG respond to."""
    rng = np.random.default_rng(seed)
    h, w = size
    img = np.zeros((h, w, 3), np.uint8)
    for _ in range(25):
        c = tuple(int(v) for v in rng.integers(0, 255, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(4, 25)), c, -1)
        else:
            cv2.rectangle(
                img, (x, y), (x + int(rng.integers(5, 40)), y + int(rng.integers(5, 40))), c, -1
            )
    return img


def write_synthetic_images(folder: Path, n: int, seed: int = 0, prefix: str = "img") -> Path:
    """Write ``n`` synthetic PNGs (``synthetic_image(seed + i)``) as ``{prefix}{i:03d}.png``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        img = cv2.cvtColor(synthetic_image(seed + i), cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(folder / f"{prefix}{i:03d}.png"), img)
    return folder


@pytest.fixture
def image_folder(tmp_path: Path):
    """Factory: write ``n`` synthetic PNGs (seeds offset by ``seed``) into a new folder."""

    def make(name: str, n: int, seed: int = 0) -> Path:
        (tmp_path / name).mkdir()
        return write_synthetic_images(tmp_path / name, n, seed)

    return make


# -- service fixtures ---------------------------------------------------------------------------
#: A cheap weight-free hierarchy for service tests (the service code does not depend on it).
SERVICE_CONFIG = {
    "name": "service-test",
    "tiers": [{"methods": ["hog", "gist"], "k": 5}, {"methods": ["gist", "sad"], "k": 1}],
}
#: Synthetic positions: reference i lies ~11 m north of reference i - 1.
BASE_LAT, BASE_LON, STEP_LAT = -27.4770, 153.0280, 1e-4


def copy_gp(gardens_point: Path, traverse: str, dest: Path, n: int) -> Path:
    """The first ``n`` images of a Gardens Point traverse, copied into ``dest``."""
    import shutil

    dest.mkdir(parents=True)
    for p in sorted((gardens_point / traverse).iterdir())[:n]:
        shutil.copy(p, dest / p.name)
    return dest


def write_positions(refs: Path, csv: Path) -> Path:
    """A metadata CSV giving the images of ``refs`` (in name order) the synthetic positions
    :data:`BASE_LAT`, :data:`BASE_LON` + i * :data:`STEP_LAT`."""
    rows = ["name,lat,lon"] + [
        f"{p.name},{BASE_LAT + i * STEP_LAT:.7f},{BASE_LON:.7f}"
        for i, p in enumerate(sorted(refs.iterdir()))
    ]
    csv.write_text("\n".join(rows) + "\n")
    return csv


@pytest.fixture(scope="session")
def service_index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A built index over the first 20 Gardens Point day_right images, with positions."""
    from hmpf.config import parse_config
    from indexer.build import BuildOptions, build

    base = tmp_path_factory.mktemp("service")
    refs = copy_gp(gardens_point, "day_right", base / "refs", 20)
    csv = write_positions(refs, base / "meta.csv")
    index = base / "index"
    build(
        parse_config(SERVICE_CONFIG),
        refs,
        index,
        metadata=csv,
        options=BuildOptions(workers=1, progress=False),
    )
    return index


def default_sigint() -> None:
    """``preexec_fn`` of a subprocess that must stop on Ctrl-C as on a terminal, even where the
    tests run as a background job (a shell starts those with SIGINT ignored, and a child
    inherits that)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@contextmanager
def cnn_runtime_as(name: str) -> Iterator[None]:
    """Run the block with CNN runtime ``name``; the previous setting comes back after."""
    saved = runtime._cnn_runtime, os.environ.get("HMPF_CNN_RUNTIME")
    runtime.set_cnn_runtime(name)
    try:
        yield
    finally:
        runtime._cnn_runtime = saved[0]
        if saved[1] is None:
            os.environ.pop("HMPF_CNN_RUNTIME", None)
        else:
            os.environ["HMPF_CNN_RUNTIME"] = saved[1]
