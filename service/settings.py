"""Service settings: environment variables with the prefix ``HMPF_`` and an optional YAML file.

Precedence: keyword arguments (the ``hmpf-serve`` flags) > environment > settings file >
defaults. The file is named by ``HMPF_SETTINGS_FILE`` (or ``hmpf-serve --settings``) and holds
the same keys without the prefix::

    index: /srv/hmpf/index
    port: 8000
    keys_file: /etc/hmpf/keys.yaml
    workers: 2
    experience_log: /var/lib/hmpf/experiences   # record accepted frames (off when unset)

Unknown keys in the file, and unknown ``HMPF_*`` environment variables, are errors (a typo
must not silently fall back to a default). The core's own variables (``HMPF_DATASETS``,
``HMPF_CACHE_DIR``, ``HMPF_THREADS``, ``HMPF_CNN_RUNTIME``), the test suite's
(``HMPF_REQUIRE_DATASETS``, ``HMPF_REQUIRE_BROWSER``, ``HMPF_REQUIRE_HAPROXY``,
``HMPF_SCREENSHOT``, ``HMPF_CHROMIUM``; set for every process a test run starts) and the client's
(``HMPF_API_KEY``, read by ``hmpf-replay``) are allowed.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Mapping
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, PydanticBaseSettingsSource, SettingsConfigDict

from hmpf.errors import ConfigError
from hmpf.experience_log import (
    DEFAULT_MAX_BYTES,
    DEFAULT_SEGMENT_BYTES,
    DEFAULT_SYNC_EVERY,
    DEFAULT_SYNC_INTERVAL_S,
)
from hmpf.methods.registry import format_validation_error

__all__ = ["CORE_ENV", "Settings", "load_settings"]

PREFIX = "HMPF_"
#: ``HMPF_*`` variables that belong to the core (hmpf) or its client, not to the service.
CORE_ENV = frozenset(
    {
        "DATASETS",
        "CACHE_DIR",
        "THREADS",
        "CNN_RUNTIME",
        "REQUIRE_DATASETS",
        "REQUIRE_BROWSER",
        "REQUIRE_HAPROXY",
        "SCREENSHOT",
        "CHROMIUM",
        "SETTINGS_FILE",
        "API_KEY",
    }
)


class Settings(BaseSettings):
    """Everything the service reads at start-up."""

    model_config = SettingsConfigDict(
        env_prefix=PREFIX, extra="forbid", frozen=True, case_sensitive=False
    )

    index: Path = Field(Path("index"), description="index folder (hmpf-index build --index)")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    # -- security ----------------------------------------------------------------------------
    auth: bool = Field(True, description="require X-API-Key; false only on purpose (warned)")
    keys_file: Path | None = Field(None, description="API keys (hashed), see hmpf-serve keys")
    # -- limits ------------------------------------------------------------------------------
    max_upload_bytes: int = Field(10 * 2**20, ge=1024, description="per image")
    max_pixels: int = Field(40_000_000, ge=64, description="width x height, from the header")
    max_batch: int = Field(16, ge=1, description="images per /v1/localize/batch request")
    decode_side: int = Field(
        1024,
        ge=0,
        description="working size: an image whose shorter side is at least twice this is "
        "decoded at 1/2, 1/4 or 1/8 of its size, its shorter side kept at or above it; 0: "
        "always the full size",
    )
    max_decode_bytes: int = Field(
        256 * 2**20,
        ge=2**20,
        description="pixels the decoder may hold for one request's images (3 bytes each, as "
        "if decoded at once: service/images.py decode_cost); more is a 413",
    )
    max_top_k: int = Field(50, ge=1)
    workers: int = Field(
        0, ge=0, description="query threads and extraction threads (0: one per core)"
    )
    queue: int = Field(8, ge=0, description="queries waiting beyond the workers, then 503")
    threads_per_worker: int = Field(0, ge=0, description="torch/OpenCV threads (0: auto)")
    retry_after_s: int = Field(1, ge=1)
    # -- connections (service/server.py) ------------------------------------------------------
    max_connections: int = Field(
        128,
        ge=1,
        description="requests in progress at once; one more gets 503 with Retry-After "
        "(/healthz, /readyz and /metrics are always answered)",
    )
    max_idle_connections: int = Field(
        64,
        ge=1,
        description="connections carrying no request (new ones before their headers, kept-alive "
        "ones between requests); one more closes the one idle the longest",
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        description="time for a request's line and headers, from the connection or the "
        "previous answer; then 408 and the connection is closed",
    )
    body_timeout_s: float = Field(
        60.0, gt=0, description="time for a request's whole body after its headers; then 408"
    )
    keep_alive_s: int = Field(5, ge=1, description="an idle kept-alive connection is closed")
    max_header_bytes: int = Field(
        16 * 1024, ge=1024, description="request line and headers; more is a 431"
    )
    # -- answers -----------------------------------------------------------------------------
    accept_threshold: float | None = Field(
        None,
        description="Combined quality (z-score) an answer needs to be accepted; None: the "
        "index config's acceptance.threshold",
    )
    approx_k: int | None = Field(
        None,
        ge=1,
        description="rows an approximate tier-1 search re-scores exactly per method (its FAISS "
        "candidates); None: max(256, 4 x tier-1 k). More keeps more of the exact top 100 at "
        "a large map's cost in reads and time (docs/scale.md)",
    )
    faiss_params: dict[str, str] = Field(
        default_factory=dict,
        description="tier 1's FAISS search parameters on top of the version's own, per "
        "method id or '*' for every approximate method, e.g. {'*': 'k_factor_front=2'} or "
        "{'gem': 'nprobe=64'} (HMPF_FAISS_PARAMS as JSON); a method that is not approximate "
        "or a parameter its type lacks stops the start (a reload keeps the old version)",
    )
    # -- sequence mode ----------------------------------------------------------------------
    sequence_key: SecretStr | None = Field(
        None,
        min_length=16,
        description="key that signs the vehicles' track tokens (every replica the same); "
        "None: the key in sequence_key_file",
    )
    sequence_key_file: Path | None = Field(
        None,
        description="file holding the signing key, created (0600) when missing; None: "
        "INDEX/.sequence-key, shared by every server on the same index folder",
    )
    track_max_age_s: float = Field(
        600.0, gt=0, description="a track token older than this restarts the vehicle's track"
    )
    # -- replicas -----------------------------------------------------------------------------
    watch_current_s: float = Field(
        0.0,
        ge=0,
        le=3600,
        description="look at the index's CURRENT every this many seconds and load the "
        "version it names when it changes, as POST /v1/index/reload does (replicas behind a "
        "balancer: e.g. 2); 0: only POST /v1/index/reload switches versions",
    )
    # -- experience recording (service/recording.py) -----------------------------------------
    experience_log: Path | None = Field(
        None,
        description="folder of the experience log: frames answered with an accepted match "
        "of p_correct >= experience_min_p_correct are appended there, for `hmpf-index add "
        "--experiences`; one service per folder; None: no recording",
    )
    experience_min_p_correct: float = Field(
        0.99,
        ge=0,
        le=1,
        description="the p_correct an accepted answer needs to be recorded (an answer "
        "without p_correct, from a version without a confidence model, never is)",
    )
    experience_modes: Annotated[tuple[Literal["sequence", "single"], ...], NoDecode] = Field(
        ("sequence",),
        min_length=1,
        description="answers recorded by where they come from: sequence (the filter's "
        "estimate), single (one frame); several as a list or comma-separated",
    )
    experience_features: bool = Field(
        True,
        description="record each frame's features with it (as the answering version's "
        "methods extracted them: about 110 KB per frame with the default preset), so that "
        "`hmpf-index add --experiences` into that version need not extract them again",
    )
    experience_lead_frames: int = Field(
        2,
        ge=0,
        le=16,
        description="a lock's lead-in: per vehicle in sequence mode, from its track's start "
        "or an off-map answer until its next recorded frame, the last frames not recorded "
        "are kept in memory, and those within 30 s before that frame are recorded before it "
        "as `lead` frames, which a merge places from the recorded frames after them (the "
        "places a vehicle passed before the filter was sure get experiences too); 0: off",
    )
    experience_lead_bytes: int = Field(
        32 << 20,
        ge=0,
        description="memory for the lead-in frames of every vehicle together (images as "
        "uploaded); over it the vehicle heard from longest ago loses its frames",
    )
    experience_queue: int = Field(
        64, ge=1, description="frames waiting for the disk; one more is dropped (counted)"
    )
    experience_max_bytes: int = Field(
        DEFAULT_MAX_BYTES,
        ge=2**20,
        description="the log's size bound; over it its oldest segments are deleted (counted)",
    )
    experience_segment_bytes: int = Field(
        DEFAULT_SEGMENT_BYTES,
        ge=64 * 1024,
        description="segment size: the unit the bound and prune delete in (at most half of "
        "experience_max_bytes)",
    )
    experience_sync_every: int = Field(
        DEFAULT_SYNC_EVERY, ge=1, description="records between fsyncs at most"
    )
    experience_sync_s: float = Field(
        DEFAULT_SYNC_INTERVAL_S,
        gt=0,
        le=3600,
        description="seconds a recorded frame waits for its fsync at most",
    )
    log_level: str = "info"

    @field_validator("experience_log", mode="before")
    @classmethod
    def _empty_is_off(cls, value: Any) -> Any:
        # HMPF_EXPERIENCE_LOG= (empty) turns recording off; it must not mean the current folder.
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("experience_modes", mode="before")
    @classmethod
    def _split_modes(cls, value: Any) -> Any:
        if isinstance(value, str):  # the environment: sequence,single (or a JSON list)
            value = value.strip().strip("[]").replace('"', "").replace("'", "")
            value = [m.strip() for m in value.split(",") if m.strip()]
        return tuple(dict.fromkeys(value)) if isinstance(value, list | tuple) else value

    @model_validator(mode="after")
    def _check(self) -> Settings:
        if self.auth and self.keys_file is None:
            raise ValueError(
                "auth is on but no keys_file is set: set HMPF_KEYS_FILE (create keys with "
                "`hmpf-serve keys add`), or HMPF_AUTH=false to run without authentication"
            )
        if 2 * self.experience_segment_bytes > self.experience_max_bytes:
            raise ValueError(
                f"experience_segment_bytes ({self.experience_segment_bytes}) must be at most "
                f"half of experience_max_bytes ({self.experience_max_bytes}): the bound "
                "deletes whole segments"
            )
        log = self.experience_log
        if log is not None and log.exists() and not log.is_dir():
            raise ValueError(f"experience_log: {str(log)!r} is not a folder")
        return self

    @property
    def worker_count(self) -> int:
        return self.workers or (os.cpu_count() or 1)

    @property
    def thread_count(self) -> int:
        """Compute threads per worker so that workers x threads <= cores."""
        if self.threads_per_worker:
            return self.threads_per_worker
        return max(1, (os.cpu_count() or 1) // self.worker_count)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings, env_settings, _FileSource(settings_cls))


_file_data: ContextVar[dict[str, Any] | None] = ContextVar("hmpf_settings_file", default=None)


class _FileSource(PydanticBaseSettingsSource):
    """The YAML file named by ``HMPF_SETTINGS_FILE`` (read by :func:`load_settings`)."""

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return (_file_data.get() or {}).get(field_name), field_name, False

    def __call__(self) -> dict[str, Any]:
        return dict(_file_data.get() or {})


def _read_file(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read settings file {str(path)!r}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of settings")
    names = set(Settings.model_fields)
    for key in data:
        if key not in names:
            raise ConfigError(f"{path}: unknown setting {key!r}{_hint(str(key), names)}")
    return data


def _hint(key: str, names: set[str]) -> str:
    close = difflib.get_close_matches(key, sorted(names), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _check_env(env: Mapping[str, str]) -> None:
    names = {n.upper() for n in Settings.model_fields}
    for var in env:
        up = var.upper()
        if not up.startswith(PREFIX):
            continue
        key = up[len(PREFIX) :]
        if key not in names and key not in CORE_ENV:
            hint = _hint(key.lower(), set(Settings.model_fields))
            raise ConfigError(f"unknown setting in the environment: {var}{hint}")


def load_settings(file: str | Path | None = None, **overrides: Any) -> Settings:
    """Settings from ``overrides`` > the environment > ``file`` (or ``HMPF_SETTINGS_FILE``).

    ``None`` overrides are ignored (unset command-line flags).

    Raises:
        ConfigError: an unknown key or variable, or an invalid value (naming it).
    """
    _check_env(os.environ)
    file = file or os.environ.get(PREFIX + "SETTINGS_FILE")
    token = _file_data.set(_read_file(Path(file)) if file else {})
    try:
        return Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, "settings")) from None
    finally:
        _file_data.reset(token)
