"""Index builds on a real local Ray cluster (``hmpf-index build ... --ray ADDRESS``).

A head node (no CPU: it only coordinates) and two worker nodes of one CPU each are started on
this machine for this module (in a temp dir of their own) and always stopped. They use Ray's
own node address: Ray 2.60 rewrites a loopback address given to ``ray.init`` into that one,
so a cluster bound to 127.0.0.1 only cannot be joined by address. Each Ray build must equal
a local build of the same Gardens Point images bit for bit (every data file's sha256 in the
manifest), also when an extraction actor is killed mid-build (Ray restarts it and retries
its batch) and when the driver is killed (CURRENT untouched; ``--resume`` finishes).

The config covers each kind of extraction: handcrafted global (HOG, Gist) and local (KAZE,
ragged keypoints) methods, and CNN methods (GeM, NetVLAD) whose VLAD centroids are fitted on
the driver and shipped to the actors.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hmpf.datasets import list_images
from indexer import distributed
from indexer.build import BuildOptions, add, build
from indexer.cli import main
from indexer.distributed import RayOptions, VersionMismatchError

N_IMAGES = 16
CONFIG = """
name: ray-test
methods:
  netvlad: {clusters: 8}
  kaze: {max_keypoints: 100}
tiers:
  - {methods: [gist, netvlad, gem], k: 4}
  - {methods: [kaze, hog], k: 1}
"""
N_METHODS = 5
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def inputs(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(config file, folder of the first N_IMAGES day_right images as symlinks)."""
    root = tmp_path_factory.mktemp("ray_inputs")
    config = root / "c.yaml"
    config.write_text(CONFIG)
    images = root / "images"
    images.mkdir()
    for p in list_images(gardens_point / "day_right")[:N_IMAGES]:
        (images / p.name).symlink_to(p)
    return config, images


@pytest.fixture(scope="module")
def local_files(inputs: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The data files (name -> sha256) of a local build (no Ray) of the same images."""
    config, images = inputs
    index = tmp_path_factory.mktemp("ray_local") / "index"
    build(config, images, index, options=BuildOptions(workers=1, progress=False))
    return _data_files(index / "v0001")


def _data_files(version: Path) -> dict[str, str]:
    files = json.loads((version / "manifest.json").read_text())["files"]
    return {name: f["sha256"] for name, f in files.items()}


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """Head node + two one-CPU worker nodes, in a temp dir of their own; always stopped."""
    ray = pytest.importorskip("ray", reason="the ray extra is not installed: pip install hmpf[ray]")
    pytest.importorskip("ray.data")
    from ray.cluster_utils import Cluster

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    temp = tempfile.mkdtemp(prefix="hmpf-ray-")  # short: Ray's socket paths have a limit
    # Ray writes the current cluster's address into <system temp>/ray even with a temp_dir
    # of its own, and fails when that folder does not exist yet (a fresh machine).
    os.makedirs(os.path.join(tempfile.gettempdir(), "ray"), exist_ok=True)
    common = {
        "object_store_memory": 200 * 1024 * 1024,
        "temp_dir": temp,
        "include_dashboard": False,
    }
    c = Cluster(initialize_head=True, head_node_args={**common, "num_cpus": 0})
    try:
        common.pop("include_dashboard")
        for _ in range(2):
            c.add_node(num_cpus=1, **common)
        c.wait_for_nodes()
        yield c
    finally:
        if ray.is_initialized():
            ray.shutdown()
        c.shutdown()
        shutil.rmtree(temp, ignore_errors=True)


def _ray_options(cluster: Any) -> BuildOptions:
    return BuildOptions(
        workers=1, progress=False, ray=RayOptions(address=cluster.address, batch_size=2)
    )


def _features_done(index: Path) -> int:
    """Feature files written so far (fitted state excluded)."""
    features = index / ".build" / "features"
    if not features.exists():
        return 0
    return sum(len(list(d.rglob("*.npz"))) for d in features.iterdir() if d.name != "fitted")


def _images_done(index: Path) -> int:
    """Images whose features of every method are written (what a resume reuses)."""
    features = index / ".build" / "features"
    dirs = [d for d in features.iterdir() if d.name != "fitted"] if features.exists() else []
    if len(dirs) < N_METHODS:
        return 0
    done = [{p.stem for p in d.rglob("*.npz")} for d in dirs]
    return len(set.intersection(*done))


def _actor_pids(cluster: Any) -> list[int]:
    """Processes of the cluster's extraction actors (children of its raylets)."""
    raylets = {
        info.process.pid
        for node in cluster.list_all_nodes()
        for info in node.all_processes.get("raylet", [])
    }
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().decode(errors="replace")
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid in raylets and "Extractor" in cmdline:
            pids.append(int(entry.name))
    return pids


def test_ray_build_equals_local_build(inputs, local_files, cluster, tmp_path):
    config, images = inputs
    index = tmp_path / "index"
    summary = build(config, images, index, options=_ray_options(cluster))
    assert summary.images == N_IMAGES and summary.resumed == 0
    assert _data_files(index / "v0001") == local_files


def test_killed_worker_is_retried_and_build_unchanged(inputs, local_files, cluster, tmp_path):
    config, images = inputs
    index = tmp_path / "index"
    killed: list[tuple[int, int]] = []  # (pid, features done when killed)
    stop = threading.Event()

    def killer() -> None:
        while not stop.is_set():
            done = _features_done(index)
            pids = _actor_pids(cluster)
            if done >= 2 * N_METHODS and pids:  # two images in: the actors are busy
                os.kill(pids[0], signal.SIGKILL)
                killed.append((pids[0], done))
                return
            time.sleep(0.05)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    try:
        summary = build(config, images, index, options=_ray_options(cluster))
    finally:
        stop.set()
        thread.join()
    assert killed, "no actor was killed (the build ended first)"
    assert killed[0][1] < N_IMAGES * N_METHODS, "killed after every feature was done"
    assert summary.images == N_IMAGES
    assert _data_files(index / "v0001") == local_files


def test_killed_driver_leaves_current_and_resume_finishes(inputs, local_files, cluster, tmp_path):
    config, images = inputs
    index = tmp_path / "index"
    first = tmp_path / "first"
    first.mkdir()
    for p in sorted(images.iterdir())[:2]:
        (first / p.name).symlink_to(p.resolve())
    build(config, first, index, options=BuildOptions(workers=1, progress=False))  # v0001
    cmd = [sys.executable, "-m", "indexer.cli", "build", "--config", str(config)]
    cmd += ["--images", str(images), "--index", str(index), "--quiet"]
    cmd += ["--ray", cluster.address]
    proc = subprocess.Popen(cmd, cwd=REPO, stderr=subprocess.PIPE, text=True)
    # Generous: with both cores busy the test took 181 s and failed with `resumed` 0, as if
    # the old 120 s deadline had passed before two images were done and the driver was
    # killed with none finished; with this deadline the same load passes (160 s). Killing
    # early now fails with its cause.
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and proc.poll() is None:
        if _images_done(index) >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, f"build ended before it could be killed: {proc.stderr.read()}"
    assert _images_done(index) >= 2, "the build did not finish two images in 600 s"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    assert (index / "CURRENT").read_text().strip() == "v0001"
    assert not (index / "v0002").exists()
    summary = build(config, images, index, options=_ray_options(cluster), resume=True)
    assert summary.version == "v0002" and summary.images == N_IMAGES
    assert summary.resumed >= 2
    assert _data_files(index / "v0002") == local_files


def _split(images: Path, root: Path, n_first: int) -> tuple[Path, Path]:
    """The images as two folders: the first ``n_first`` and the rest (symlinks)."""
    first, more = root / "first", root / "more"
    first.mkdir()
    more.mkdir()
    for k, p in enumerate(sorted(images.iterdir())):
        ((first if k < n_first else more) / p.name).symlink_to(p.resolve())
    return first, more


def test_ray_add_equals_local_add(inputs, cluster, tmp_path):
    """``add --ray`` extracts only the new images on the cluster (the fitted state comes from
    the parent version): the new version equals a local ``add`` bit for bit."""
    config, images = inputs
    first, more = _split(images, tmp_path, 10)
    local = BuildOptions(workers=1, progress=False)
    versions = {}
    for name, opts in (("local", local), ("ray", _ray_options(cluster))):
        index = tmp_path / name
        build(config, first, index, options=local)
        summary = add(index, more, options=opts)
        assert summary.images == N_IMAGES and summary.extracted == N_IMAGES - 10
        versions[name] = _data_files(index / "v0002")
    assert versions["ray"] == versions["local"]


def test_cli_ray_without_address_starts_and_stops_a_local_instance(
    inputs, local_files, cluster, tmp_path
):
    """``hmpf-index build --ray`` alone: a Ray instance of its own (``ray.init(address=
    "local")``), stopped at the end; the same version as a local build. (A subprocess, as a user
    runs it: Ray Data keeps per-process state tied to the first cluster it ran on.)"""
    config, images = inputs
    index = tmp_path / "index"
    cmd = [sys.executable, "-m", "indexer.cli", "build", "--config", str(config)]
    cmd += ["--images", str(images), "--index", str(index), "--quiet", "--ray", "--workers", "1"]
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"published v0001 with {N_IMAGES} references" in proc.stdout
    assert _data_files(index / "v0001") == local_files
    assert cluster.remaining_processes_alive()  # the test cluster was not stopped


def test_worker_with_other_packages_is_refused(inputs, cluster, tmp_path, monkeypatch):
    """The actors compare their package versions with the driver's: a node with another
    numpy (here: the driver claims one) stops the build with one clear error."""
    config, images = inputs
    real = distributed._package_versions()
    monkeypatch.setattr(distributed, "_package_versions", lambda: {**real, "numpy": "0.0.test"})
    index = tmp_path / "index"
    with pytest.raises(VersionMismatchError, match=r"numpy .* \(driver 0\.0\.test\)"):
        build(config, images, index, options=_ray_options(cluster))
    assert not (index / "CURRENT").exists()


def test_unreachable_address_fails_fast(inputs, tmp_path, capsys):
    pytest.importorskip("ray.data")
    config, images = inputs
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    rc = main(
        ["build", "--config", str(config), "--images", str(images)]
        + ["--index", str(tmp_path / "i"), "--quiet", "--ray", f"127.0.0.1:{port}"]
    )
    assert rc == 2 and time.monotonic() - t0 < 60
    assert f"--ray 127.0.0.1:{port}: no Ray cluster reachable there" in capsys.readouterr().err


def test_without_the_extra_one_line_error(tmp_path, monkeypatch, capsys):
    """No Ray installed (simulated: the import fails): exit 2, one line naming the extra,
    before any image is read."""
    monkeypatch.setitem(sys.modules, "ray", None)
    rc = main(
        ["build", "--config", "handcrafted", "--images", str(tmp_path / "none")]
        + ["--index", str(tmp_path / "i"), "--ray"]
    )
    err = capsys.readouterr().err
    assert rc == 2
    assert err.strip().splitlines() == [f"hmpf-index: error: {distributed.RAY_HINT}"]
