"""Domain errors of hmpf.

Every error the core raises on bad input derives from :class:`HmpfError`, so callers (the CLI,
the indexer, the HTTP service) can map them to a clean message or status code in one place::

    HmpfError
    ├── ImageError            an image could not be read or decoded (names the file)
    ├── ConfigError           a hierarchy/method configuration is invalid (names the key)
    │   └── UnknownMethodError    a method name that is not registered (lists the valid ones)
    ├── DatasetError          an image folder or ground-truth file is unusable
    ├── WeightsError          a CNN weight file is missing or not in the expected layout
    └── MissingDependencyError    an optional extra is not installed (says what to install)
"""

from __future__ import annotations


class HmpfError(Exception):
    """Base class of every error hmpf raises on purpose."""


class ImageError(HmpfError):
    """An image is empty, corrupt, truncated or not an image at all."""

    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = reason
        super().__init__(f"cannot read image {source!r}: {reason}")

    def __reduce__(self) -> tuple[type, tuple[str, str]]:  # picklable across processes
        return (type(self), (self.source, self.reason))


class ConfigError(HmpfError):
    """A configuration file or value is invalid."""


class UnknownMethodError(ConfigError):
    """A method name that is not in the registry."""

    def __init__(self, name: str, available: list[str], kind: str = "method") -> None:
        self.name = name
        self.available = available
        self.kind = kind
        super().__init__(f"unknown {kind} {name!r}; available {kind}s: {', '.join(available)}")

    def __reduce__(self) -> tuple[type, tuple[str, list[str], str]]:
        return (type(self), (self.name, self.available, self.kind))


class DatasetError(HmpfError):
    """An image folder, a ground-truth or metadata file cannot be used."""


class WeightsError(HmpfError):
    """A weight file is missing, unreadable or not in the layout its loader expects."""


class MissingDependencyError(HmpfError):
    """An optional dependency is missing; the message says which extra to install."""
