"""``GET /v1/index`` (what is loaded) and ``POST /v1/index/reload`` (admin: switch versions)."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter

from hmpf.errors import HmpfError
from hmpf.index import layout
from service.deps import AdminKey, EngineDep, MetricsDep, VehicleKey
from service.engine import Acceptance, Engine
from service.errors import ERROR_RESPONSES, ApiError
from service.schemas import IndexInfo

__all__ = ["router"]

log = logging.getLogger("hmpf.service")
router = APIRouter(tags=["index"], responses=ERROR_RESPONSES)
#: Manifest entries of a method that ``/v1/index`` reports.
_METHOD_KEYS = ("type", "kind", "version", "dim", "faiss", "params")


@router.get("/v1/index", response_model=IndexInfo)
def index_info(key: VehicleKey, engine: EngineDep) -> dict[str, Any]:
    """The loaded index version: counts, methods, config, build time."""
    return _index_info(engine)


@router.post("/v1/index/reload")
async def reload(key: AdminKey, engine: EngineDep, metrics: MetricsDep) -> dict[str, Any]:
    """Switch to the index's current version; running queries finish on the old one."""
    try:
        old, new = await engine.reload()
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
    metrics.set_index(new)
    return {"previous": old, "version": new, "changed": old != new}


def _index_info(engine: Engine) -> dict[str, Any]:
    loaded = engine.current
    reader = loaded.reader
    manifest = reader.manifest
    summary = manifest.get("summary", {})
    return {
        "root": str(engine.root),
        "version": reader.version,
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
        "acceptance": _acceptance(loaded.acceptance),
        "loaded_at": loaded.loaded_at,
    }


def _acceptance(acc: Acceptance) -> dict[str, Any]:
    def model(m: Any, threshold: float | None) -> dict[str, Any] | None:
        if m is None or threshold is None:
            return None
        return {"features": list(m.features), "threshold": threshold}

    single = model(acc.model, acc.model_threshold)
    return {
        "rule": "quality" if single is None else "p_correct",
        "threshold": acc.threshold,
        "model": single,
        "sequence_model": model(acc.sequence_model, acc.sequence_threshold),
    }
