"""Extraction workers die with the process that started them.

``hmpf-index`` extracts handcrafted features in a process pool (the forkserver context: a
forkserver, a resource tracker and the workers, about 170 MB each). Killed with SIGKILL, the
parent cannot shut the pool down; the workers must still go (PR_SET_PDEATHSIG, see
:func:`hmpf.runtime.die_with_parent`) rather than wait for work for ever.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="process tree read from /proc"
)

#: A long extraction in 2 worker processes (Gist on the same few images, many times over).
SCRIPT = """
import sys
from pathlib import Path

from hmpf.features import extract_images
from hmpf.methods.registry import create_method

paths = sorted(Path(sys.argv[1]).iterdir()) * 2000
extract_images(paths, {"gist": create_method("gist")}, workers=2)
"""


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) of a process, or None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = text[text.rindex(")") + 2 :].split()
    return fields[0], int(fields[1])


def descendants(root: int) -> set[int]:
    """Every live process under ``root`` (children, their children, ...)."""
    parent = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (st := _stat(int(entry.name))) is not None:
            parent[int(entry.name)] = st[1]
    found: set[int] = set()
    frontier = {root}
    while frontier:
        frontier = {p for p, pp in parent.items() if pp in frontier} - found
        found |= frontier
    return found


def alive(pid: int) -> bool:
    st = _stat(pid)
    return st is not None and st[0] not in ("Z", "X")  # a zombie has exited


def test_workers_die_when_the_extraction_is_killed(tmp_path: Path) -> None:
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        ok, buf = cv2.imencode(".jpg", rng.integers(0, 256, (240, 320, 3), dtype=np.uint8))
        (images / f"{i}.jpg").write_bytes(buf.tobytes())
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(images)], cwd=ROOT, env=env)
    try:
        # The forkserver, the resource tracker and two workers.
        deadline = time.monotonic() + 60
        pool = descendants(proc.pid)
        while len(pool) < 4:
            assert proc.poll() is None, "the extraction ended early"
            assert time.monotonic() < deadline, f"no worker pool after 60 s: {pool}"
            time.sleep(0.1)
            pool = descendants(proc.pid)
        time.sleep(0.5)  # the workers are extracting
        pool = descendants(proc.pid)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    deadline = time.monotonic() + 5
    while any(alive(p) for p in pool) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = sorted(p for p in pool if alive(p))
    names = {p: Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ")[:120] for p in left}
    for p in left:  # clean up before failing
        os.kill(p, signal.SIGKILL)
    assert not left, f"still running 5 s after the parent was killed: {names}"
