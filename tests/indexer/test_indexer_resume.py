"""Atomic publish and resume: a build killed with SIGKILL leaves CURRENT untouched and
``build --resume`` finishes it without redoing finished images, equal to a clean build."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import h5py
import numpy as np

from hmpf.index import IndexReader
from indexer.build import BuildOptions, build
from indexer.maintenance import verify
from tests.conftest import default_sigint, synthetic_image

CONFIG = """
name: resume-test
tiers:
  - {methods: [hog, gist], k: 4}
  - {methods: [kaze], k: 1}
"""


def _folder(path: Path, n: int) -> Path:
    path.mkdir()
    for i in range(n):
        img = cv2.cvtColor(synthetic_image(i, (240, 320)), cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(path / f"img{i:03d}.png"), img)
    return path


def _contents(version: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name in ("references.h5", "local.h5"):
        with h5py.File(version / name) as f:
            f.visititems(
                lambda k, o, name=name: (
                    out.__setitem__(f"{name}:{k}", o[()]) if isinstance(o, h5py.Dataset) else None
                )
            )
    return out


def test_kill_then_resume_equals_clean_build(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(CONFIG)
    images = _folder(tmp_path / "imgs", 30)
    first = _folder(tmp_path / "first", 2)
    index = tmp_path / "index"
    opts = BuildOptions(workers=1, progress=False)
    build(config, first, index, options=opts)  # v0001: must survive the kill
    cmd = [
        sys.executable,
        "-m",
        "indexer.cli",
        "build",
        "--config",
        str(config),
        "--images",
        str(images),
        "--index",
        str(index),
        "--workers",
        "1",
        "--quiet",
    ]
    proc = subprocess.Popen(cmd, cwd=Path(__file__).resolve().parents[2])
    features = index / ".build" / "features"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        done = len(list(features.rglob("*.npz"))) if features.exists() else 0
        if done >= 3 * 8 or proc.poll() is not None:  # 3 methods x 8 images
            break
        time.sleep(0.05)
    assert proc.poll() is None, "build finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (index / "CURRENT").read_text().strip() == "v0001"
    assert verify(index) == []
    with IndexReader(index) as r:
        assert r.n == 2
    summary = build(config, images, index, options=opts, resume=True)
    assert summary.version == "v0002" and summary.images == 30
    assert summary.resumed >= 8
    assert not (index / ".build").exists()
    clean = tmp_path / "clean"
    build(config, images, clean, options=opts)
    got, want = _contents(index / "v0002"), _contents(clean / "v0001")
    assert set(got) == set(want)
    for k in want:
        assert np.array_equal(got[k], want[k]), k


def test_ctrl_c_during_extraction_is_one_line_and_exit_130(tmp_path):
    """SIGINT to the whole process group (what a terminal's Ctrl-C does) while the
    extraction pool runs: exit 130, one line on stderr (no traceback from the parent or the
    workers), CURRENT untouched, and --resume finishes the job."""
    config = tmp_path / "c.yaml"
    config.write_text(CONFIG)
    images = _folder(tmp_path / "imgs", 30)
    index = tmp_path / "index"
    cmd = [sys.executable, "-m", "indexer.cli", "build", "--config", str(config)]
    cmd += ["--images", str(images), "--index", str(index), "--workers", "2", "--quiet"]
    proc = subprocess.Popen(
        cmd,
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=default_sigint,
    )
    features = index / ".build" / "features"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        done = len(list(features.rglob("*.npz"))) if features.exists() else 0
        if done >= 3 * 2 or proc.poll() is not None:  # >= 1 image with all 3 methods
            break
        time.sleep(0.05)
    assert proc.poll() is None, "build finished before it could be interrupted"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.splitlines() == [
        "hmpf-index: interrupted; the current version is untouched "
        "(rerun with --resume to continue)"
    ]
    assert not (index / "CURRENT").exists()
    summary = build(
        config, images, index, options=BuildOptions(workers=1, progress=False), resume=True
    )
    assert summary.images == 30 and summary.resumed >= 1
