"""docker/Dockerfile, docker/compose.yaml, .dockerignore and the container-test scripts agree
with the project. ``make lint`` runs hadolint on the Dockerfile; these checks read the files.
The images themselves are built and run by ``make container-test`` (podman; minutes), not by
the test suite; these checks catch a broken file before that."""

from __future__ import annotations

import fnmatch
import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import yaml

from service.settings import load_settings

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = (ROOT / "docker" / "Dockerfile").read_text()
COMPOSE = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _env(text: str) -> dict[str, str]:
    """ENV assignments of the Dockerfile (``ENV A=1 \\`` continuation lines)."""
    joined = text.replace("\\\n", " ")
    out: dict[str, str] = {}
    for line in joined.splitlines():
        if line.startswith("ENV "):
            out.update(re.findall(r"(\w+)=(\S+)", line))
    return out


def test_dockerfile_pins_the_projects_cpu_torch_and_runs_unprivileged() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    pin = next(
        d for d in project["project"]["optional-dependencies"]["cnn"] if d.startswith("torch")
    )
    assert f"ARG TORCH_VERSION={pin.split('==')[1]}" in DOCKERFILE
    assert "download.pytorch.org/whl/cpu" in DOCKERFILE
    assert len(re.findall(r"^FROM ", DOCKERFILE, re.M)) >= 2  # multi-stage
    user = re.findall(r"^USER (\S+)", DOCKERFILE, re.M)[-1]
    assert user.split(":")[0] not in ("0", "root")
    assert "HEALTHCHECK" in DOCKERFILE and "/readyz" in DOCKERFILE
    for src in re.findall(r"^COPY (?!--from)(\S+)", DOCKERFILE, re.M):
        assert (ROOT / src).exists(), src


def test_service_container_settings_are_valid(tmp_path: Path, monkeypatch) -> None:
    env = {**_env(DOCKERFILE), **COMPOSE["services"]["service"]["environment"]}
    for k, v in env.items():
        if k.startswith("HMPF_"):
            monkeypatch.setenv(k, re.sub(r"\$\{\w+:-(\w*)\}", r"\1", str(v)))
    monkeypatch.setenv("HMPF_KEYS_FILE", str(tmp_path / "keys.yaml"))
    s = load_settings()
    assert s.host == "0.0.0.0" and s.port == 8000 and s.auth is True
    assert str(s.index).startswith("/data/")


def test_compose_indexer_job_and_service_share_the_index_volume() -> None:
    svc = COMPOSE["services"]
    indexer, service = svc["indexer"], svc["service"]
    assert service["depends_on"]["indexer"]["condition"] == "service_completed_successfully"
    assert indexer["restart"] == "no"
    assert "hmpf-index build" in " ".join(indexer["command"])
    images = [v for v in indexer["volumes"] if ":/images" in v]
    assert images and images[0].endswith(":ro")  # reference images read-only
    assert "index:/data" in indexer["volumes"]
    assert "index:/data:ro" in service["volumes"]
    assert "index" in COMPOSE["volumes"]
    assert all(p.startswith("127.0.0.1:") for p in service["ports"])
    assert service["environment"]["HMPF_KEYS_FILE"].startswith("/run/secrets/")
    # Sequence mode signs track tokens with a key in a writable volume (the index is ro).
    key_file = service["environment"]["HMPF_SEQUENCE_KEY_FILE"]
    assert "state:/state" in service["volumes"] and key_file.startswith("/state/")
    assert "state" in COMPOSE["volumes"] and "/state" in DOCKERFILE


def _instructions(text: str) -> list[str]:
    """The Dockerfile's instructions, continuation lines joined, comments dropped."""
    lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]
    return [s.strip() for s in "\n".join(lines).replace("\\\n", " ").splitlines() if s.strip()]


INSTRUCTIONS = _instructions(DOCKERFILE)


def _stages() -> dict[str, str]:
    """Stage name -> its FROM image."""
    out = {}
    for ins in INSTRUCTIONS:
        m = re.match(r"FROM (\S+) AS (\S+)$", ins, re.I)
        if m:
            out[m.group(2)] = m.group(1)
    return out


def _arg_default(name: str) -> str:
    m = re.search(rf"^ARG {name}=(.*)$", DOCKERFILE, re.M)
    assert m, name
    return m.group(1).strip()


def test_two_final_targets_on_one_base_argument() -> None:
    stages = _stages()
    assert {"indexer", "service", "runtime"} <= stages.keys()
    assert stages["indexer"] == stages["service"] == "runtime"
    assert _arg_default("PYTHON_IMAGE") == "python:3.11-slim-bookworm"
    # every stage that is not FROM another stage (or the empty wheels stage) is the base argument
    for name, image in stages.items():
        assert image in stages or image in ("${PYTHON_IMAGE}", "scratch"), (name, image)
    # the service image is the default target: the last stage
    last = [i for i in INSTRUCTIONS if i.upper().startswith("FROM ")][-1]
    assert last.endswith("AS service")


def test_every_pip_step_gets_the_optional_ca_secret_and_local_wheels() -> None:
    pip_runs = [i for i in INSTRUCTIONS if i.startswith("RUN") and "pip install" in i]
    assert len(pip_runs) >= 4
    for run in pip_runs:
        assert "--mount=type=secret,id=ca_bundle,required=false" in run, run
        assert "--mount=type=bind,from=wheels,target=/wheels" in run, run
        assert "PIP_CERT=/run/secrets/ca_bundle" in run, run
    # the CA bundle is never copied into an image
    assert not re.search(r"^(COPY|ADD) .*\.(crt|pem)\b", DOCKERFILE, re.M)


def test_torch_only_from_the_cpu_index_and_never_in_a_service_without_cnn() -> None:
    pin = next(d for d in PROJECT["project"]["optional-dependencies"]["cnn"] if "torch" in d)
    assert _arg_default("TORCH_VERSION") == pin.split("==")[1]
    assert _arg_default("TORCH_INDEX_URL") == "https://download.pytorch.org/whl/cpu"
    service_build = DOCKERFILE[DOCKERFILE.index("AS build-service") :]
    assert 'import torch" 2>/dev/null; then' in service_build  # fails the build if torch got in
    extras = PROJECT["project"]["optional-dependencies"]
    for extra in _arg_default("SERVICE_EXTRAS").split(","):
        assert extra in extras, extra


def test_runtime_is_unprivileged_and_keeps_the_service_paths() -> None:
    for stage in ("indexer", "service"):
        body = DOCKERFILE[DOCKERFILE.index(f"AS {stage}\n") :]
        user = re.search(r"^USER (\S+)", body, re.M)
        assert user and user.group(1) == "10001:10001", stage
    assert "groupadd --system --gid 10001 hmpf" in DOCKERFILE


def _ignored(path: str, patterns: list[str]) -> bool:
    """Docker's .dockerignore rule for one path: the last matching pattern wins."""
    ignored = False
    for pat in patterns:
        neg = pat.startswith("!")
        pat = pat[1:] if neg else pat
        pat = pat.rstrip("/")
        parts = path.split("/")
        prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        if pat.startswith("**/"):
            hit = any(fnmatch.fnmatch(p, pat[3:]) for p in parts)
        else:
            hit = any(fnmatch.fnmatch(p, pat) for p in prefixes)
        if hit:
            ignored = not neg
    return ignored


def test_dockerignore_sends_only_what_the_images_copy() -> None:
    patterns = [
        ln.strip()
        for ln in (ROOT / ".dockerignore").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    copied = set()
    for ins in INSTRUCTIONS:
        if ins.startswith("COPY") and "--from=" not in ins:
            copied.update(ins.split()[1:-1])
    assert copied
    for src in copied:
        assert (ROOT / src).exists(), src
        assert not _ignored(src, patterns), src
    for path in (
        ".venv/bin/python",
        ".git/HEAD",
        "index/default/CURRENT",
        "results/eval.json",
        "hmpf/__pycache__/x.pyc",
        "tests/packaging/test_docker_files.py",
        "docker/keys.yaml",
    ):
        assert _ignored(path, patterns), path


def test_compose_builds_each_service_from_its_target() -> None:
    stages = _stages()
    for name in ("indexer", "service"):
        build = COMPOSE["services"][name]["build"]
        assert build["target"] == name and build["target"] in stages
        assert build["dockerfile"] == "docker/Dockerfile" and build["context"] == ".."


def test_container_scripts_parse_and_are_executable() -> None:
    for name in ("container-test.sh", "local-base.sh", "index-job.sh"):
        path = ROOT / "docker" / name
        assert os.access(path, os.X_OK), name
        shell = "bash" if path.read_text().startswith("#!/usr/bin/env bash") else "sh"
        subprocess.run([shell, "-n", str(path)], check=True)
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^container-test:", makefile, re.M)
    assert "docker/container-test.sh" in makefile


def test_record_writes_the_container_run(tmp_path: Path) -> None:
    """``docker/record.py`` (``RECORD=path make container-test``; standard library only, as
    the host's python3 runs it): the steps, sizes, answer and served config land in the record
    the docs are made from."""
    answer = {"match": {"name": "Image051.jpg", "reference_id": 51, "score": 2.5, "p_correct": 0.9}}
    (tmp_path / "answer.json").write_text(json.dumps(answer))
    (tmp_path / "index.json").write_text(json.dumps({"config": {"name": "default", "tiers": []}}))
    out = tmp_path / "record.json"
    fields = ["total=12", "base_kept=yes", "torch=no", "indexer_mb=1800", "service_mb=830"]
    cmd = [sys.executable, str(ROOT / "docker" / "record.py"), str(out)]
    cmd += [str(tmp_path / "answer.json"), *fields, "base_mb=209", "--"]
    cmd += ["base image=0", "build indexer image=7", "localize a night frame=1"]
    subprocess.run(cmd, check=True)
    rec = json.loads(out.read_text())
    steps = {"base image": 0, "build indexer image": 7, "localize a night frame": 1}
    assert rec["steps_s"] == steps
    assert rec["total_s"] == 12 and rec["base_image_kept"] is True
    assert rec["images_mb"] == {"indexer": 1800, "service": 830, "base": 209}
    assert rec["service_has_torch"] is False and rec["preset"] == "default"
    assert rec["answer"]["reference_id"] == 51 and rec["answer"]["accepted"] is None
    assert rec["config"] == {"name": "default", "tiers": []}
    assert rec["commit"] and rec["machine_details"]["cores"] == os.cpu_count()
