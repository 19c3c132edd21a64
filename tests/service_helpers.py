"""Helpers of the service tests that run real servers and real indexes (no fixtures here:
each test module scopes its own).

* :class:`Server`: ``hmpf-serve`` in a subprocess on a free loopback port.
* :data:`GP_CONFIG` and :func:`build_gp_index`: an index over Gardens Point day_right with a
  CNN (GeM on the bundled backbone) and Gist in tier 1, the configuration night frames are
  matched with.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from hmpf.config import parse_config
from hmpf.hierarchy import ScoreFn
from indexer.build import BuildOptions, build
from tests.conftest import copy_gp, default_sigint

__all__ = [
    "BUILD_OPTIONS",
    "GP_CONFIG",
    "ROOT",
    "Server",
    "build_gp_index",
    "free_port",
    "nan_in_final_tier",
]

ROOT = Path(__file__).resolve().parent.parent
#: GeM (a CNN on the bundled backbone) + Gist narrow, Gist + HOG + SAD decide.
GP_CONFIG = {
    "name": "e2e",
    "tiers": [{"methods": ["gem", "gist"], "k": 5}, {"methods": ["gem", "gist", "hog"], "k": 1}],
}
BUILD_OPTIONS = BuildOptions(workers=1, progress=False)


def build_gp_index(
    gardens_point: Path, base: Path, n: int, config: dict[str, Any] | None = None
) -> Path:
    """An index (``base/index``) over the first ``n`` day_right images (copied to
    ``base/refs``), for ``config`` (default :data:`GP_CONFIG`)."""
    refs = copy_gp(gardens_point, "day_right", base / "refs", n)
    out = base / "index"
    build(parse_config(config or GP_CONFIG), refs, out, options=BUILD_OPTIONS)
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_ok(args: list[str], cwd: Path, env: dict[str, str], timeout: float = 600) -> str:
    """``args`` run in ``cwd`` with ``env``: its standard output; an assertion error with
    both outputs when it fails (without pip's warnings about package folders it does not
    find, which bury its error)."""
    proc = subprocess.run(
        args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )
    err = "\n".join(
        line for line in proc.stderr.splitlines() if not line.startswith("WARNING: Location ")
    )
    assert proc.returncode == 0, f"{args} -> {proc.returncode}\n{proc.stdout}\n{err}"
    return proc.stdout


#: What the project's wheel is built from (the files the Dockerfile copies too).
WHEEL_SOURCES = ("pyproject.toml", "README.md", "LICENSE", "hmpf", "indexer", "service")


def build_wheel(base: Path, env: dict[str, str]) -> Path:
    """The project's wheel, built in ``base`` (outside the checkout) from a copy of
    :data:`WHEEL_SOURCES`, offline (no build isolation): its path."""
    assert not base.resolve().is_relative_to(ROOT)
    src = base / "src"
    src.mkdir()
    for name in WHEEL_SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(ROOT / name, src / name)
    run_ok(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation"]
        + ["-w", "dist", str(src)],
        base,
        env,
    )
    (wheel,) = (base / "dist").glob("hmpf-*.whl")
    return wheel


class LoggedProcess:
    """A subprocess writing stdout and stderr to ``log``; :meth:`stop` sends SIGTERM, then
    SIGKILL after ``stop_wait_s``. Subclasses set ``proc``, ``log`` and ``_out``."""

    proc: subprocess.Popen[bytes]
    log: Path
    _out: Any
    stop_wait_s = 20.0

    def output(self) -> str:
        """The log's last 4000 characters."""
        if not self._out.closed:
            self._out.flush()
        return self.log.read_text(errors="replace")[-4000:]

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(self.stop_wait_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._out.close()


class Server(LoggedProcess):
    """``hmpf-serve`` in a subprocess; stopped (SIGTERM, then SIGKILL) on exit."""

    def __init__(self, index: Path, log: Path, **env: str) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = log
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("HMPF_")}
        for k in ("HMPF_DATASETS", "HMPF_CACHE_DIR"):
            if k in os.environ:
                full_env[k] = os.environ[k]
        full_env.update({f"HMPF_{k.upper()}": v for k, v in env.items()})
        self._out = log.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "--index", str(index), "--port", str(self.port)],
            cwd=ROOT,
            env=full_env,
            stdout=self._out,
            stderr=subprocess.STDOUT,
            preexec_fn=default_sigint,
        )
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"hmpf-serve exited {self.proc.returncode}: {self.output()}")
            try:
                if httpx.get(self.url + "/readyz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.25)
        self.stop()
        raise AssertionError(f"hmpf-serve not ready after 180 s: {self.output()}")


def nan_in_final_tier(real: ScoreFn, method: str = "sad") -> ScoreFn:
    """``real`` with ``method`` scoring NaN for the first candidate it gets in a later tier
    (a method that fails on one reference: the match's score is then not a number)."""

    def score_fn(mid: str, subset: np.ndarray | None) -> np.ndarray:
        scores = np.asarray(real(mid, subset), dtype=np.float64)
        if mid == method and subset is not None:
            scores = scores.copy()
            scores[0] = np.nan
        return scores

    return score_fn


#: one sample line of the Prometheus text format: name, labels, value
_SAMPLE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(?:\{(.*)\})?\s+(\S+)$")


def metric_sum(text: str, name: str, **labels: str) -> float:
    """The sum of the samples of metric ``name`` in a /metrics ``text`` whose labels include
    ``labels``."""
    total = 0.0
    for line in text.splitlines():
        m = _SAMPLE.match(line)
        if m is None or m.group(1) != name:
            continue
        have = dict(re.findall(r'(\w+)="([^"]*)"', m.group(2) or ""))
        if all(have.get(k) == v for k, v in labels.items()):
            total += float(m.group(3))
    return total


def evaluate_frames(index: Path, frames: list[Path], positions: list[int], tolerance: int) -> dict:
    """``hmpf-eval --index``'s report (:func:`hmpf.evaluation.evaluate.evaluate_index`, in
    sequence mode too) of ``frames`` against ``index``, frame ``j`` right within
    ``+-tolerance`` references of ``positions[j]`` (frame-aligned with the references)."""
    from hmpf.evaluation.evaluate import evaluate_index
    from hmpf.index.reader import IndexReader

    reader = IndexReader(index)
    try:
        gt = np.zeros((len(frames), reader.n), dtype=bool)
        for j, i in enumerate(positions):
            gt[j, max(0, i - tolerance) : i + tolerance + 1] = True
        return evaluate_index(reader, frames, gt, f"frames +-{tolerance}", sequence=True)
    finally:
        reader.close()
