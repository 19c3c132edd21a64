"""The built wheel works on its own: every command, run from a folder outside the checkout,
in a fresh virtual environment where hmpf comes from the wheel and nothing else.

The wheel is built (``pip wheel --no-deps --no-build-isolation``, offline) from a copy of the
files a source distribution holds, so no ``build/`` or ``*.egg-info`` lands in the checkout.
The fresh venv gets only the wheel; the heavy dependencies (torch, FAISS, ...) are made
visible by a ``.pth`` line naming this interpreter's site-packages. A plain path line does
not run that folder's own ``.pth`` files, so an editable install of the checkout there stays
inactive, and the test asserts that ``hmpf`` is imported from the fresh venv.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.service_helpers import WHEEL_SOURCES, build_wheel, run_ok

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel_env(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, str]]:
    """(bin folder of the fresh venv, a work folder outside the checkout, its environment)."""
    base = tmp_path_factory.mktemp("wheel")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PIP_"))}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    pip = [sys.executable, "-m", "pip"]
    wheel = build_wheel(base, env)

    venv = base / "venv"
    run_ok([sys.executable, "-m", "venv", "--without-pip", str(venv)], base, env)
    python = venv / "bin" / "python"
    run_ok(
        [*pip, "--python", str(python), "install", "-q", "--no-deps", "--no-index", str(wheel)],
        base,
        env,
    )
    fresh_site = Path(
        run_ok(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], base, env
        ).strip()
    )
    # The dependencies: this (the project's) environment's site-packages, found from its prefix.
    (fresh_site / "_hmpf_test_dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")

    work = base / "work"
    work.mkdir()
    env["HMPF_CACHE_DIR"] = str(base / "cache")
    return venv / "bin", work, env


def test_sources_are_what_the_dockerfile_builds_from() -> None:
    """The Docker images install hmpf from the same files (a missing LICENSE would fail it);
    the container's own scripts (docker/) are copied beside them."""
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    copied = set()
    for line in re.findall(r"^COPY (?!--from)(.+)$", dockerfile, re.M):
        copied.update(src for src in line.split()[:-1] if not src.startswith("docker/"))
    assert copied == set(WHEEL_SOURCES)


def test_wheel_holds_the_presets_and_the_license(wheel_env) -> None:
    bindir, work, env = wheel_env
    out = run_ok(
        [
            str(bindir / "python"),
            "-c",
            "import hmpf, importlib.metadata as m\n"
            "from hmpf.config import preset_names\n"
            "print(hmpf.__file__)\n"
            "print(' '.join(preset_names()))\n"
            "meta = m.metadata('hmpf')\n"
            "print(meta['License-Expression'], meta.get_all('License-File'))\n"
            "import sys, hmpf.client\n"  # the client: a base dependency (httpx), no torch
            "print([d.split('>')[0] for d in meta.get_all('Requires-Dist') if ';' not in d])\n"
            "print(hmpf.client.__file__, 'torch' in sys.modules)\n"
            "from importlib.resources import files\n"  # the shipped confidence models
            "print(files('hmpf').joinpath('presets/acceptance/default.json').is_file())\n",
        ],
        work,
        env,
    )
    where, presets, license_, base_deps, client, shipped = out.splitlines()
    assert shipped == "True", "the default preset's shipped models are package data"
    venv = bindir.parent.resolve()
    assert Path(where).resolve().is_relative_to(venv), where  # the wheel's copy, not ROOT
    assert not Path(where).resolve().is_relative_to(ROOT)
    assert set(presets.split()) == {
        str(p.relative_to(ROOT / "configs").with_suffix(""))
        for p in (ROOT / "configs").rglob("*.yaml")
    }
    assert license_ == "MIT ['LICENSE']"
    assert "'httpx'" in base_deps, base_deps
    client_file, torch_loaded = client.split()
    assert Path(client_file).resolve().is_relative_to(venv) and torch_loaded == "False", client


def test_wheel_holds_the_inspection_page(wheel_env) -> None:
    """The page's files (service/static) are package data: hmpf-serve serves them from the
    installed wheel."""
    bindir, work, env = wheel_env
    out = run_ok(
        [
            str(bindir / "python"),
            "-c",
            "from service.routes.inspect import STATIC\n"
            "print(STATIC)\n"
            "print(' '.join(sorted(p.name for p in STATIC.iterdir())))\n",
        ],
        work,
        env,
    )
    where, files = out.splitlines()
    assert Path(where).resolve().is_relative_to(bindir.parent.resolve()), where
    assert files.split() == sorted(p.name for p in (ROOT / "service" / "static").iterdir())
    assert {"inspect.html", "inspect.css", "inspect.js"} <= set(files.split())


def test_every_command_runs_from_the_wheel(wheel_env, gardens_point: Path) -> None:
    bindir, work, env = wheel_env
    for command in (
        "hmpf-eval",
        "hmpf-calibrate",
        "hmpf-index",
        "hmpf-serve",
        "hmpf-replay",
        "hmpf-experiences",
    ):
        assert (bindir / command).is_file(), command
        assert "usage:" in run_ok([str(bindir / command), "--help"], work, env)
        assert run_ok([str(bindir / command), "--version"], work, env).startswith(command)
    assert "--config" in run_ok([str(bindir / "hmpf-eval"), "--help"], work, env)

    # A handful of frame-aligned images: references day_right, queries night_right.
    for folder, traverse in (("refs", "day_right"), ("queries", "night_right")):
        (work / folder).mkdir()
        for p in sorted((gardens_point / traverse).iterdir())[:8]:
            (work / folder / p.name).symlink_to(p)

    # hmpf-calibrate with its default pool (the preset calibration-pool, every method),
    # the smallest search: 2 training and 2 test stretches of 2 frames.
    run_ok(
        [
            str(bindir / "hmpf-calibrate"),
            *("--reference", "refs", "--query", "queries", "--tolerance", "1"),
            *("--block", "2", "--k1", "2", "--k2", "1", "--samples", "10", "--refine", "2"),
            *("--workers", "1", "--quiet", "--out", "cal"),
        ],
        work,
        env,
    )
    assert (work / "cal" / "calibrated.yaml").is_file()

    # An index from a preset name, then from the calibrated config's path.
    for config, index in (("single-tier", "idx-preset"), ("cal/calibrated.yaml", "idx-path")):
        run_ok(
            [
                str(bindir / "hmpf-index"),
                *("build", "--config", config, "--images", "refs", "--index", index),
                *("--workers", "1", "--quiet"),
            ],
            work,
            env,
        )
        assert (work / index / "CURRENT").is_file()
    run_ok([str(bindir / "hmpf-index"), "verify", "--index", "idx-preset"], work, env)

    # A name that is neither a file nor a preset: a one-line error listing the presets.
    proc = subprocess.run(
        [
            str(bindir / "hmpf-index"),
            "build",
            "--config",
            "handcraftd",
            "--images",
            "refs",
            "--index",
            "idx-bad",
        ],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode != 0
    assert "neither a file nor a preset" in proc.stderr and "handcrafted" in proc.stderr
