"""API keys: a file of ``tenant:key`` lines, kept in memory only as SHA-256 digests.

``tenant_for(key)`` hashes the presented key and compares it with every stored digest in constant time
(``hmac.compare_digest``), so neither the keys nor the timing of a lookup reveal anything. The HTTP API takes
``Authorization: Bearer KEY``; the gRPC servers take the same keys in ``authorization`` metadata and get
``tenant_for`` as a plain callable.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path

TENANT_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MIN_KEY_LENGTH = 16


class KeyFileError(ValueError):
    """The API key file is missing, empty or has a malformed line."""


def _check_pair(tenant: str, key: str) -> None:
    if not TENANT_RE.match(tenant):
        raise KeyFileError(f"tenant {tenant!r}: use 1-64 letters, digits, '_', '.', '-'")
    if len(key) < MIN_KEY_LENGTH or any(c.isspace() for c in key):
        raise KeyFileError(f"tenant {tenant!r}: keys need >= {MIN_KEY_LENGTH} characters and no spaces")


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).digest()


@dataclass
class KeyStore:
    """Tenants by hashed API key. Build with ``from_file``, ``from_pairs`` or ``generate``."""

    _entries: list[tuple[bytes, str]] = field(default_factory=list)  # (sha256(key), tenant)

    @classmethod
    def from_pairs(cls, pairs: list[tuple[str, str]]) -> "KeyStore":
        """From (tenant, key) pairs; tenant names match ``TENANT_RE``, keys have >= 16 characters, no duplicates."""
        store, seen = cls(), set()
        for tenant, key in pairs:
            _check_pair(tenant, key)
            d = _digest(key)
            if d in seen:
                raise KeyFileError(f"tenant {tenant!r}: the same key is listed twice")
            seen.add(d)
            store._entries.append((d, tenant))
        return store

    @classmethod
    def from_file(cls, path: str | Path) -> "KeyStore":
        """Read ``tenant:key`` lines (blank lines and ``#`` comments ignored). A tenant may have several keys."""
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise KeyFileError(f"{path}: cannot read the API key file ({exc.strerror})") from None
        pairs = []
        for n, line in enumerate(text.splitlines(), 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            tenant, sep, key = line.partition(":")
            if not sep:
                raise KeyFileError(f"{path}:{n}: expected 'tenant:key'")
            try:
                _check_pair(tenant.strip(), key.strip())
            except KeyFileError as exc:
                raise KeyFileError(f"{path}:{n}: {exc}") from None
            pairs.append((tenant.strip(), key.strip()))
        if not pairs:
            raise KeyFileError(f"{path}: no 'tenant:key' line")
        return cls.from_pairs(pairs)

    @classmethod
    def generate(cls, tenant: str = "local") -> tuple["KeyStore", str]:
        """A store with one fresh random key for ``tenant``; returns (store, key). The key is not kept."""
        key = secrets.token_urlsafe(32)
        return cls.from_pairs([(tenant, key)]), key

    def tenant_for(self, key: str | None) -> str | None:
        """The tenant of ``key``, or None (unknown, empty or missing). Every digest is compared."""
        if not key:
            return None
        d, found = _digest(key), None
        for digest, tenant in self._entries:
            if hmac.compare_digest(digest, d):
                found = tenant
        return found

    @property
    def tenants(self) -> list[str]:
        return sorted({t for _, t in self._entries})

    def __len__(self) -> int:
        return len(self._entries)


def bearer_key(header: str | None) -> str | None:
    """The key of an ``Authorization: Bearer KEY`` header value (scheme case-insensitive), else None."""
    if not header:
        return None
    scheme, _, value = header.strip().partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        return None
    return value.strip()
