"""What the routes take from the app, as ``Annotated`` dependencies.

* :data:`EngineDep`, :data:`SettingsDep`, :data:`MetricsDep`, :data:`TrackerDep`: the
  objects ``create_app`` keeps in ``app.state``.
* :data:`VehicleKey`, :data:`AdminKey`: the caller's API key (header ``X-API-Key``, declared
  with :class:`~fastapi.security.APIKeyHeader` so that ``/docs`` shows the scheme), checked
  against the keys file for the route's role; ``None`` when the service runs without auth.

They are ``async def`` because they do not block: FastAPI calls a plain ``def`` dependency in
its thread pool, a hop that costs more than the work itself.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader

from service.auth import ApiKey, KeyStore
from service.engine import Engine
from service.errors import ApiError
from service.metrics import Metrics
from service.settings import Settings
from service.vehicle import Tracker

__all__ = [
    "AdminKey",
    "EngineDep",
    "MetricsDep",
    "SettingsDep",
    "TrackerDep",
    "VehicleKey",
    "api_key_header",
    "authorize",
    "is_admin",
]


async def get_engine(request: Request) -> Engine:
    engine: Engine = request.app.state.engine
    return engine


async def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


async def get_metrics(request: Request) -> Metrics:
    metrics: Metrics = request.app.state.metrics
    return metrics


async def get_tracker(request: Request) -> Tracker:
    tracker: Tracker = request.app.state.tracker
    return tracker


EngineDep = Annotated[Engine, Depends(get_engine)]
TrackerDep = Annotated[Tracker, Depends(get_tracker)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]

#: ``auto_error=False``: a missing key is answered by :func:`_authorize` in the API's own
#: error format (401 + ``WWW-Authenticate: ApiKey``), not by FastAPI's default.
API_KEY_HEADER = "X-API-Key"
api_key_header = APIKeyHeader(
    name=API_KEY_HEADER,
    auto_error=False,
    description="API key (create one with `hmpf-serve keys add`); not needed when the "
    "service runs with auth=false",
)
PresentedKey = Annotated[str | None, Security(api_key_header)]


def authorize(request: Request, presented: str | None, role: str) -> ApiKey | None:
    """The key ``presented`` if its role allows ``role`` routes (None without auth).

    Raises:
        ApiError: 401 for a missing or unknown key, 403 for a key whose role falls short.
    """
    keys: KeyStore | None = request.app.state.keys
    if keys is None:
        return None
    key = keys.check(presented)
    if key is None:
        raise ApiError(
            401,
            "unauthorized",
            "missing or invalid API key (header X-API-Key)",
            {"WWW-Authenticate": "ApiKey"},
        )
    if not key.allows(role):
        raise ApiError(403, "forbidden", f"this key's role may not {role}-only routes")
    return key


def _authorize(role: str) -> Callable[[Request, str | None], Awaitable[ApiKey | None]]:
    """A dependency admitting keys whose role allows ``role`` routes (401 / 403 otherwise)."""

    async def check(request: Request, presented: PresentedKey) -> ApiKey | None:
        return authorize(request, presented, role)

    return check


def is_admin(key: ApiKey | None) -> bool:
    """Whether the caller may see what admin keys see: an admin key, or any caller of a
    service without auth (``None``: anyone may reload there)."""
    return key is None or key.allows("admin")


VehicleKey = Annotated[ApiKey | None, Depends(_authorize("vehicle"))]
AdminKey = Annotated[ApiKey | None, Depends(_authorize("admin"))]
