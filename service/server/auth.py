"""API keys: the keys file (REPNET_API_KEYS_FILE) and the constant-time check both transports use."""

from __future__ import annotations

import hashlib
import hmac
import logging
from pathlib import Path

log = logging.getLogger(__name__)

# What a refused call is told, on both transports: nothing about which part was wrong.
UNAUTHENTICATED_MESSAGE = "missing or invalid API key"
BEARER = "bearer "


def _digest(key: str) -> bytes:
    """A fixed-length stand-in for `key`, so that comparing takes the same time whatever its length."""
    return hashlib.sha256(key.encode("utf-8", "surrogateescape")).digest()


class ApiKeys:
    """The keys a client may present. Only their SHA-256 digests are kept, and a candidate is compared
    with every one of them by hmac.compare_digest, so neither the time taken nor anything logged
    tells which key, or which part of one, a wrong candidate missed. A key is never logged."""

    def __init__(self, keys: list[str]) -> None:
        if not keys:
            raise ValueError("an API keys file must hold at least one key")
        self._digests = [_digest(k) for k in keys]

    @classmethod
    def read(cls, path: Path) -> ApiKeys:
        """One key per line; blank lines and lines starting with # are skipped, spaces around a key
        are not part of it. OSError if the file cannot be read, ValueError if it holds no key."""
        lines = (line.strip() for line in path.read_text(encoding="utf-8").splitlines())
        keys = [line for line in lines if line and not line.startswith("#")]
        if not keys:
            raise ValueError(f"{path}: no API key in the file (one per line; # starts a comment)")
        log.info("API keys: %d from %s", len(keys), path)  # never the keys
        return cls(keys)

    def __len__(self) -> int:
        return len(self._digests)

    def accepts(self, candidate: str) -> bool:
        """`candidate` is one of the keys (constant time in the candidate and over all keys)."""
        digest = _digest(candidate)
        found = False
        for known in self._digests:  # no early exit: every key is compared
            found |= hmac.compare_digest(digest, known)
        return found

    def accepts_header(self, authorization: str | None) -> bool:
        """An `Authorization: Bearer KEY` header value (HTTP header or gRPC metadata) holds a key."""
        if authorization is None or authorization[: len(BEARER)].lower() != BEARER:
            return False
        return self.accepts(authorization[len(BEARER) :].strip())


def client_identity(authorization: str | None, peer: str) -> str:
    """Who a call comes from, for the limits per client: its API key (as a digest: the key itself is
    kept nowhere) when it sends one, else its address without the port (gRPC's peer `ipv4:1.2.3.4:5`
    -> `ipv4:1.2.3.4`, `ipv6:[::1]:5` -> `ipv6:[::1]`). Without keys, clients behind one NAT or proxy
    share one identity. An unchecked key is no way around the limit: the interceptor refuses a call
    whose key is not one of the service's before it is counted."""
    if authorization is not None and authorization[: len(BEARER)].lower() == BEARER:
        return "key:" + _digest(authorization[len(BEARER) :].strip()).hex()[:16]
    if peer.startswith(("ipv4:", "ipv6:")):
        return peer.rsplit(":", 1)[0]
    return peer
