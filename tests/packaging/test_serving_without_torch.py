"""Serving needs no torch: ``pip install 'hmpf[serve]'`` into a fresh virtual environment (the
project's wheel and its dependencies from the package index, as a service image installs
them: no torch comes with it), then ``hmpf-serve`` there answers a real night image over
HTTP from an index the project's environment (with torch) built with a CNN method, with the
match the project's environment finds.

* ``import torch`` fails in that environment (and neither torch nor onnx is installed);
* the descriptors it computes equal the project environment's (the same stored ONNX models,
  the same onnxruntime and preprocessing), and so do the answers of every query;
* a version built before versions stored their models is refused there at start (exit 2)
  with what to do, instead of failing at the first query.

Marked ``slow`` (an install of about 30 s, one venv shared by every test here):
``pytest -m 'not slow'`` leaves it out; ``make test`` runs it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.imageio import load_image
from hmpf.index import IndexReader
from indexer.build import BuildOptions, build
from tests.conftest import copy_gp
from tests.service_helpers import build_wheel, free_port, run_ok

pytestmark = pytest.mark.slow
pytest.importorskip("torch")  # the index is built here, with torch

#: Multi-scale GeM on the bundled EfficientNet-Lite0 (two stored models) and Gist.
CONFIG = {
    "name": "serve-without-torch",
    "methods": {"gem": {"scales": [1.0, 0.5]}},
    "tiers": [{"methods": ["gem", "gist"], "k": 4}, {"methods": ["gem", "gist"], "k": 1}],
}
N_REFS = 12
#: Night queries (indices into night_right), inside the references' stretch.
QUERIES = (1, 4, 7, 10)
ATOL = 1e-3  # descriptor values at float16 precision (tests/hmpf/index/test_onnx_in_index.py)


@dataclass(frozen=True)
class ServeEnv:
    """The serve venv's bin folder, a work folder outside the checkout, the environment."""

    bin: Path
    work: Path
    env: dict[str, str]

    def cmd(self, name: str, *args: str) -> list[str]:
        return [str(self.bin / name), *args]


@pytest.fixture(scope="module")
def serve_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServeEnv]:
    """A fresh venv with ``hmpf[serve]`` installed from the project's wheel: its bin folder,
    a work folder outside the checkout and the environment to run commands in. Removed after
    this module's tests (about 600 MB: the suite's disk use stays bounded)."""
    base = tmp_path_factory.mktemp("serve-venv")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PIP_", "HMPF_"))}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    work = base / "work"
    work.mkdir()
    env["HMPF_CACHE_DIR"] = str(base / "cache")
    t0 = time.monotonic()
    wheel = build_wheel(base, env)
    venv = base / "venv"
    run_ok([sys.executable, "-m", "venv", str(venv)], base, env)
    # A normal install, dependencies included: what it pulls in is what a server gets.
    run_ok([str(venv / "bin" / "pip"), "install", "-q", f"{wheel}[serve]"], work, env)
    seconds = time.monotonic() - t0
    size = sum(p.stat().st_size for p in venv.rglob("*") if p.is_file() and not p.is_symlink())
    print(f"\nserve venv: installed in {seconds:.0f} s, {size / 1e6:.0f} MB")
    yield ServeEnv(venv / "bin", work, env)
    shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(scope="module")
def indexes(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Built here (torch installed): ``new`` stores its models, ``old`` is built as
    hmpf-index did before versions stored them."""
    import indexer.build

    base = tmp_path_factory.mktemp("serve-indexes")
    refs = copy_gp(gardens_point, "day_right", base / "refs", N_REFS)
    config = parse_config(CONFIG)
    options = BuildOptions(workers=1, progress=False)
    build(config, refs, base / "new", options=options)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(indexer.build, "write_models", lambda out, methods: [])
        build(config, refs, base / "old", options=options)
    return {"new": base / "new", "old": base / "old"}


@pytest.fixture(scope="module")
def nights(gardens_point: Path) -> list[Path]:
    every = sorted((gardens_point / "night_right").iterdir())
    return [every[i] for i in QUERIES]


def _python(serve_env: ServeEnv, code: str) -> subprocess.CompletedProcess[str]:
    """Run ``code`` with the serve venv's python, outside the checkout."""
    return subprocess.run(
        serve_env.cmd("python", "-c", code),
        cwd=serve_env.work,
        env=serve_env.env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_serve_install_has_no_torch(serve_env: ServeEnv) -> None:
    out = _python(serve_env, "import torch")
    assert out.returncode != 0 and "No module named 'torch'" in out.stderr
    code = (
        "import importlib.util as u, hmpf, onnxruntime, faiss, h5py, cv2, fastapi, uvicorn;"
        "print(hmpf.__file__, [m for m in ('torch', 'onnx') if u.find_spec(m)])"
    )
    out = _python(serve_env, code)
    assert out.returncode == 0, out.stderr
    where, missing = out.stdout.split(maxsplit=1)
    assert where.startswith(str(serve_env.bin.parent))  # the venv's hmpf, not the checkout
    assert missing.strip() == "[]"


QUERY_SCRIPT = """
import json, sys
from hmpf.imageio import load_image
from hmpf.index import IndexReader
reader = IndexReader(sys.argv[1])
hier = reader.hierarchy()
out = []
for p in sys.argv[2:]:
    feats = reader.extract_query(load_image(p))
    match = hier.run(reader.scorer(feats), reader.n).match
    out.append({"match": reader.refs.names[match], "gem": feats["gem"].astype(float).tolist()})
print(json.dumps({"answers": out, "torch": "torch" in sys.modules}))
"""


def test_queries_equal_the_project_environments(
    serve_env: ServeEnv, indexes: dict[str, Path], nights: list[Path]
) -> None:
    code = QUERY_SCRIPT.replace("sys.argv[1]", repr(str(indexes["new"]))).replace(
        "sys.argv[2:]", repr([str(p) for p in nights])
    )
    out = _python(serve_env, code)
    assert out.returncode == 0, out.stderr
    there = json.loads(out.stdout.strip().splitlines()[-1])
    assert there["torch"] is False
    with IndexReader(indexes["new"]) as reader:
        hier = reader.hierarchy()
        for p, got in zip(nights, there["answers"], strict=True):
            feats = reader.extract_query(load_image(p))
            assert got["match"] == reader.refs.names[hier.run(reader.scorer(feats), reader.n).match]
            diff = np.abs(np.asarray(got["gem"]) - feats["gem"].astype(float)).max()
            assert diff <= ATOL, (p.name, diff)


def test_hmpf_serve_answers_a_night_image(
    serve_env: ServeEnv, indexes: dict[str, Path], nights: list[Path]
) -> None:
    env = {**serve_env.env, "HMPF_AUTH": "false"}
    port = free_port()
    log = serve_env.work / "serve.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen(
            serve_env.cmd("hmpf-serve", "--index", str(indexes["new"]), "--port", str(port)),
            cwd=serve_env.work,
            env=env,
            stdout=fh,
            stderr=subprocess.STDOUT,
        )
        try:
            url = f"http://127.0.0.1:{port}"
            deadline = time.monotonic() + 120
            while True:
                assert proc.poll() is None, log.read_text()
                assert time.monotonic() < deadline, log.read_text()
                try:
                    if httpx.get(url + "/readyz", timeout=2).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.25)
            night = nights[1]
            r = httpx.post(
                url + "/v1/localize",
                files={"image": (night.name, night.read_bytes(), "image/jpeg")},
                timeout=60,
            )
            assert r.status_code == 200, r.text
            answer = r.json()
        finally:
            proc.terminate()
            proc.wait(30)
    with IndexReader(indexes["new"]) as reader:
        feats = reader.extract_query(load_image(night))
        want = reader.refs.names[reader.hierarchy().run(reader.scorer(feats), reader.n).match]
    assert answer["match"]["name"] == want
    assert answer["index_version"] == "v0001"
    assert "Traceback" not in log.read_text()


def test_a_version_without_models_is_refused_at_start(
    serve_env: ServeEnv, indexes: dict[str, Path]
) -> None:
    env = {**serve_env.env, "HMPF_AUTH": "false"}
    out = subprocess.run(
        serve_env.cmd("hmpf-serve", "--index", str(indexes["old"]), "--port", str(free_port())),
        cwd=serve_env.work,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2, out.stdout + out.stderr
    assert "stores no exported model" in out.stderr and "hmpf-index build" in out.stderr
    assert "Traceback" not in out.stderr
