"""API keys: stored as sha256 hashes with a role, checked in constant time.

Keys file (YAML; create entries with ``hmpf-serve keys add``)::

    keys:
      - name: car-17
        role: vehicle          # vehicle: localise and read the index; admin: also reload
        sha256: 9f86d0...      # sha256 of the key, hex

Keys are random 256-bit tokens (``secrets.token_urlsafe(32)``), so a plain sha256 is enough to
keep a leaked file from revealing them. Every presented key is compared against every stored
hash with :func:`hmac.compare_digest`, so the time taken does not depend on which entry (if
any) matched.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import yaml

from hmpf.errors import ConfigError

__all__ = ["ROLES", "ApiKey", "KeyStore", "add_key", "hash_key"]

Role = Literal["vehicle", "admin"]
ROLES: tuple[str, ...] = ("vehicle", "admin")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_NAME = re.compile(r"^[A-Za-z0-9_.@-]{1,64}$")


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class ApiKey:
    name: str
    role: str
    sha256: str

    def allows(self, role: str) -> bool:
        """``admin`` may do everything a ``vehicle`` may."""
        return self.role == "admin" or self.role == role


class KeyStore:
    """The keys of one keys file."""

    def __init__(self, keys: list[ApiKey]) -> None:
        self.keys = keys
        self._digests = [bytes.fromhex(k.sha256) for k in keys]

    @classmethod
    def load(cls, path: Path) -> KeyStore:
        """Read and validate a keys file (a missing file is an empty store for ``add``)."""
        return cls(_parse(path, _read(path)))

    def check(self, presented: str | None) -> ApiKey | None:
        """The entry whose hash equals ``presented``'s, or None (constant time over entries)."""
        if not presented:
            return None
        digest = hashlib.sha256(presented.encode("utf-8", "surrogateescape")).digest()
        found: ApiKey | None = None
        for key, stored in zip(self.keys, self._digests, strict=True):
            if hmac.compare_digest(digest, stored):
                found = key
        return found


def _read(path: Path) -> object:
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(
            f"keys file {str(path)!r} does not exist; create it with `hmpf-serve keys add`"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot read keys file {str(path)!r}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}") from None


def _parse(path: Path, data: object) -> list[ApiKey]:
    if data is None:
        return []
    if not isinstance(data, dict) or set(data) != {"keys"} or not isinstance(data["keys"], list):
        raise ConfigError(f"{path}: expected a mapping with one key, 'keys', holding a list")
    out: list[ApiKey] = []
    for i, entry in enumerate(data["keys"]):
        where = f"{path}: keys[{i}]"
        if not isinstance(entry, dict) or set(entry) != {"name", "role", "sha256"}:
            raise ConfigError(f"{where}: expected exactly name, role and sha256")
        name, role, digest = (str(entry[k]) for k in ("name", "role", "sha256"))
        if role not in ROLES:
            raise ConfigError(f"{where}: role {role!r} is not one of {', '.join(ROLES)}")
        if not _HEX64.match(digest):
            raise ConfigError(f"{where}: sha256 must be 64 lower-case hex digits")
        out.append(ApiKey(name, role, digest))
    names = [k.name for k in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"{path}: a key name appears twice")
    return out


def add_key(path: Path, name: str, role: str) -> str:
    """Create a key, store its hash in ``path`` (created 0600 if missing) and return the key
    (never one starting with ``-``, which a command line would take for an option)."""
    if role not in ROLES:
        raise ConfigError(f"role {role!r} is not one of {', '.join(ROLES)}")
    if not _NAME.match(name):
        raise ConfigError("key names are 1-64 characters of letters, digits and _ . @ -")
    keys = _parse(path, _read(path)) if path.exists() else []
    if any(k.name == name for k in keys):
        raise ConfigError(f"{path}: a key named {name!r} exists already")
    key = secrets.token_urlsafe(32)
    while key.startswith("-"):  # one in 64 would read as an option: `hmpf-replay --key -X...`
        key = secrets.token_urlsafe(32)
    keys.append(ApiKey(name, role, hash_key(key)))
    text = yaml.safe_dump({"keys": [k.__dict__ for k in keys]}, sort_keys=False)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return key
