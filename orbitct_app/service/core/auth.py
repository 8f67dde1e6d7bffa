"""Bearer tokens (one per person) stored only as SHA-256 hashes, each with one or more of the roles operator,
analyst and viewer."""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from orbitct_app.service.core.jsonfile import write_json_atomically
from orbitct_app.service.core.settings import Role, TokenHash, role_label

Permission = Literal["read", "motion", "scan", "analysis", "stop", "reset", "people"]

ROLES: tuple[str, ...] = ("operator", "analyst", "viewer")
# Everyone who may see the bench may press the emergency stop; only an operator may reset it; the rest is split by role.
PERMISSIONS: dict[str, frozenset[str]] = {
    "operator": frozenset({"read", "motion", "scan", "stop", "reset", "people"}),
    "analyst": frozenset({"read", "analysis", "stop"}),
    "viewer": frozenset({"read", "stop"}),
}
# The generated token of a --sim service may do everything (it never exists on real hardware).
SIM_DEV_ROLE = "sim-dev"
PERMISSIONS[SIM_DEV_ROLE] = PERMISSIONS["operator"] | PERMISSIONS["analyst"]
#: what each role is for, as the console and the refusals say it
ROLE_WORDS = {
    "operator": "moves the bench, runs scans, resets the stop, manages people",
    "analyst": "calibrates, reconstructs, plans BBs",
    "viewer": "reads only",
}
TOKEN_PREFIX = "oct_"
# A stop the web server forwards to the guard for a signed-in console user: the service's forwarding secret as the
# token, "name|role" of the user in this header
ON_BEHALF_HEADER = "X-Orbitct-On-Behalf-Of"


class TokenFileError(ValueError):
    """The tokens file cannot be read or written."""


@dataclass(frozen=True)
class Principal:
    """Who is calling: the name of their sign-in (token) and the roles it carries (one or several)."""

    name: str
    roles: tuple[str, ...]

    @property
    def role(self) -> str:
        """The roles as the console shows them: ``operator, analyst``."""
        return role_label(self.roles)

    @classmethod
    def from_label(cls, name: str, label: str) -> Principal:
        """The principal whose :attr:`role` is ``label``."""
        return cls(name=name, roles=tuple(r.strip() for r in label.split(",") if r.strip()))

    @property
    def permissions(self) -> frozenset[str]:
        """Everything its roles grant together."""
        return frozenset().union(*(PERMISSIONS.get(r, frozenset()) for r in self.roles))

    def may(self, permission: str) -> bool:
        """Whether one of its roles grants ``permission``."""
        return permission in self.permissions

    def refusal(self, permission: str) -> str:
        """Why it may not do something that needs ``permission``, in the console's words."""
        needed = [r for r in ROLES if permission in PERMISSIONS[r]]
        return (
            f"{self.name} is signed in as {self.role}; this needs the {' or '.join(needed)} role "
            f"({ROLE_WORDS[needed[0]]})"
        )

    @staticmethod
    def refusal_advice(permission: str) -> str:
        """What to do about a refusal of ``permission``: who gives the role, and where."""
        needed = next(r for r in ROLES if permission in PERMISSIONS[r])
        return (
            "ask an operator to add that role to your sign-in (the console's People page, or "
            f"`orbitct token create --role ... --role {needed}`)"
        )


def hash_token(token: str) -> str:
    """SHA-256 hex digest of a token (tokens are 256-bit random, so no slow KDF is needed)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def new_token() -> str:
    """A fresh random token."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def read_token_file(path: Path) -> list[TokenHash]:
    """Token hashes stored in ``path`` (none if the file does not exist)."""
    if not path.exists():
        return []
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
        return [TokenHash.model_validate(t) for t in raw.get("tokens", [])]
    except (OSError, ValueError, AttributeError) as exc:
        raise TokenFileError(f"{path}: not a valid tokens file ({exc})") from None


def _write_token_file(path: Path, entries: list[TokenHash]) -> None:
    """Replace ``path`` atomically with ``entries`` (readable by its owner only)."""
    body = {
        "tokens": [e.model_dump() for e in entries],
        "updated_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    write_json_atomically(path, body, private=True)


def create_token(path: Path, roles: Role | Sequence[Role], name: str = "") -> str:
    """Make a token (one person's sign-in) with ``roles``, append its hash to ``path`` and return the token (shown
    once)."""
    wanted = [roles] if isinstance(roles, str) else list(dict.fromkeys(roles))
    if not wanted or any(r not in ROLES for r in wanted):
        raise TokenFileError(f"roles must be among {', '.join(ROLES)}, got {', '.join(map(str, wanted)) or 'none'}")
    token = new_token()
    entries = read_token_file(path)
    name = name or f"{'-'.join(wanted)}-{len(entries) + 1}"
    if any(e.name == name for e in entries):
        raise TokenFileError(f"a token named {name!r} exists already in {path}; choose another name")
    entries.append(TokenHash(sha256=hash_token(token), roles=wanted, name=name))
    _write_token_file(path, entries)
    return token


def revoke_token(path: Path, key: str) -> TokenHash:
    """Remove the token whose name is ``key`` (or whose hash starts with it, 8+ hex digits); returns it."""
    entries = read_token_file(path)
    hits = [e for e in entries if e.name == key]
    if not hits and len(key) >= 8:
        hits = [e for e in entries if e.sha256.startswith(key.lower())]
    if not hits:
        known = ", ".join(e.name for e in entries) or "none"
        raise TokenFileError(f"no token named {key!r} (or with a hash starting so) in {path}; tokens: {known}")
    if len(hits) > 1:
        raise TokenFileError(
            f"{key!r} matches {len(hits)} tokens ({', '.join(e.sha256[:12] for e in hits)}); give more of the hash"
        )
    _write_token_file(path, [e for e in entries if e is not hits[0]])
    return hits[0]


class TokenRegistry:
    """Known token hashes: the configured ones plus the tokens file (re-read when it changes)."""

    def __init__(self, configured: list[TokenHash], path: Path | None, dev_token: str | None = None) -> None:
        self._configured = list(configured)
        self._dev_hash = hash_token(dev_token) if dev_token is not None else None
        self._path = path
        self._mtime: float | None = None
        self._file: list[TokenHash] = []
        self._lock = threading.Lock()

    def _entries(self) -> list[TokenHash]:
        if self._path is not None:
            try:
                mtime = self._path.stat().st_mtime
            except OSError:
                mtime = None
            with self._lock:
                if mtime != self._mtime:
                    self._file = read_token_file(self._path) if mtime is not None else []
                    self._mtime = mtime
        return self._configured + self._file

    def __len__(self) -> int:
        return len(self._entries()) + (self._dev_hash is not None)

    def authenticate(self, token: str) -> Principal | None:
        """The principal of ``token``, or None if it is unknown."""
        return self.authenticate_hash(hash_token(token))

    def authenticate_hash(self, digest: str) -> Principal | None:
        """The principal of the token whose SHA-256 is ``digest`` (a signed-in session re-checks it on each request)."""
        found: Principal | None = None
        if self._dev_hash is not None and hmac.compare_digest(self._dev_hash, digest):
            found = Principal(name="sim-dev", roles=(SIM_DEV_ROLE,))
        for entry in self._entries():
            if hmac.compare_digest(entry.sha256, digest):
                found = Principal(name=entry.name, roles=tuple(entry.roles))
        return found
