"""docker/Dockerfile and docker/compose.yaml agree with the project (no Docker engine here:
``make lint`` runs hadolint on the Dockerfile; these checks read both files)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import yaml

from service.settings import load_settings

ROOT = Path(__file__).resolve().parent.parent
DOCKERFILE = (ROOT / "docker" / "Dockerfile").read_text()
COMPOSE = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())


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
    assert indexer["image"] == service["image"]
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
