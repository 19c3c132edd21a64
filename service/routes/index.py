"""``GET /v1/index`` (what is loaded) and ``POST /v1/index/reload`` (admin: switch versions).

``/v1/index`` shows where the index lies on the server's disk and the package versions of its
build only to admin keys (other keys get null there).
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter

from hmpf.errors import HmpfError
from hmpf.index import layout
from service.deps import AdminKey, EngineDep, MetricsDep, VehicleKey, is_admin
from service.engine import Engine, Loaded
from service.errors import ApiError
from service.reloader import current_version, reload_index
from service.schemas import ErrorBody, IndexInfo, ReloadResponse

__all__ = ["router"]

log = logging.getLogger("hmpf.service")
#: The errors both routes answer: a missing or unknown key, a key whose role falls short.
_KEY_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorBody, "description": "missing or unknown API key"},
    403: {"model": ErrorBody, "description": "the key's role may not use this route"},
}
router = APIRouter(tags=["index"], responses=_KEY_ERRORS)
#: Manifest entries of a method that ``/v1/index`` reports.
_METHOD_KEYS = ("type", "kind", "version", "dim", "faiss", "params")


@router.get("/v1/index", response_model=IndexInfo)
def index_info(key: VehicleKey, engine: EngineDep) -> dict[str, Any]:
    """The loaded index version: counts, methods, config, build time (its folder on the
    server and the build's package versions: admin keys only), and the version the index's
    ``CURRENT`` names now (another one: this server has not switched yet)."""
    info = _index_info(engine)
    if not is_admin(key):
        info["root"] = None
        info["built"]["packages"] = None
    return info


@router.post(
    "/v1/index/reload",
    response_model=ReloadResponse,
    responses={
        409: {
            "model": ErrorBody,
            "description": "the current version cannot be loaded (`index_unusable`); the "
            "loaded one stays in service",
        }
    },
)
async def reload(key: AdminKey, engine: EngineDep, metrics: MetricsDep) -> dict[str, Any]:
    """Switch to the index's current version; running queries finish on the old one."""
    try:
        old, new = await reload_index(engine, metrics, "request")
    except HmpfError as exc:
        raise ApiError(
            409, "index_unusable", f"kept version {engine.current.version}: {exc}"
        ) from None
    except Exception:
        log.exception("reload of %s failed", engine.root)
        raise ApiError(
            409,
            "index_unusable",
            f"kept version {engine.current.version}: the current version could not be "
            "loaded (see the service log)",
        ) from None
    return {"previous": old, "version": new, "changed": old != new}


def _index_info(engine: Engine) -> dict[str, Any]:
    loaded = engine.current
    reader = loaded.reader
    manifest = reader.manifest
    summary = manifest.get("summary", {})
    return {
        "root": str(engine.root),
        "version": reader.version,
        "current": current_version(engine),
        "versions": layout.list_versions(engine.root),
        "references": reader.n,
        "methods": {
            mid: {k: v for k, v in info.items() if k in _METHOD_KEYS}
            for mid, info in manifest.get("methods", {}).items()
        },
        "config": manifest.get("config", {}).get("resolved", {}),
        "built": {
            "created": manifest.get("created"),
            "operation": manifest.get("operation"),
            "seconds": summary.get("seconds"),
            "images_per_s": summary.get("images_per_s"),
            "packages": manifest.get("packages", {}),
        },
        "has_positions": loaded.has_positions,
        "threshold": loaded.threshold,
        "acceptance": _acceptance(loaded),
        "loaded_at": loaded.loaded_at,
        "verification": {
            "state": loaded.verification,
            "seconds": reader.verify_seconds,
            "check_seconds": loaded.check_seconds,
            "problems": loaded.problems,
        },
    }


def _acceptance(loaded: Loaded) -> dict[str, Any]:
    out = loaded.acceptance.describe()
    if loaded.map_prior_stored is not None and loaded.profile is not None:
        out["map_prior"] = loaded.profile.map_prior
        out["map_prior_stored"] = loaded.map_prior_stored
    return out
