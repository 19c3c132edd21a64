"""Method registry: adding a method is one module plus the ``@register`` decorator."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar

from pydantic import ValidationError

from hmpf.errors import ConfigError, UnknownMethodError
from hmpf.methods.base import Method

__all__ = ["available_methods", "create_method", "get_method_class", "register"]

_REGISTRY: dict[str, type[Method]] = {}

M = TypeVar("M", bound=type[Method])


def register(cls: M) -> M:
    """Class decorator: make ``cls`` available under ``cls.name``."""
    name = cls.name
    if name in _REGISTRY and _REGISTRY[name] is not cls:
        raise RuntimeError(f"method name {name!r} registered twice")
    _REGISTRY[name] = cls
    return cls


def available_methods() -> list[str]:
    """Sorted names of every registered method."""
    return sorted(_REGISTRY)


def get_method_class(name: str) -> type[Method]:
    """The class registered as ``name``; :class:`UnknownMethodError` lists the valid names."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownMethodError(name, available_methods()) from None


def format_validation_error(exc: ValidationError, where: str) -> str:
    """One readable line per pydantic error, naming the offending key."""
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "<root>"
        if err["type"] == "extra_forbidden":
            lines.append(f"{where}: unknown key {loc!r}")
        else:
            lines.append(f"{where}: {loc}: {err['msg']}")
    return "; ".join(lines)


def create_method(name: str, params: Mapping[str, Any] | None = None) -> Method:
    """Instantiate the method registered as ``name`` with validated ``params``."""
    cls = get_method_class(name)
    try:
        config = cls.Config.model_validate(dict(params or {}))
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, f"method {name!r}")) from None
    return cls(config)
