"""Browser sessions: a bearer token exchanged once for an HttpOnly cookie, with a per-session CSRF token.

The cookie holds a random session id, never the token. The session keeps only the token's hash and
re-checks it on every request, so revoking the token ends its sessions. A state-changing request
made with the cookie must carry the session's CSRF token in the ``X-CSRF-Token`` header (a page of
another site can send the cookie, but cannot read the CSRF token nor set that header without CORS).
"""

from __future__ import annotations

import hmac
import secrets
import threading
import time
from dataclasses import dataclass

from orbitct_app.service.core.auth import Principal, TokenRegistry, hash_token

COOKIE = "orbitct_session"
CSRF_HEADER = "X-CSRF-Token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


@dataclass(frozen=True)
class Session:
    """One signed-in browser: whose token (by hash), its CSRF token and when it expires (monotonic seconds)."""

    token_sha256: str
    csrf: str
    expires: float


class SessionStore:
    """Sessions in memory (a restarted service asks every browser to sign in again)."""

    def __init__(self, tokens: TokenRegistry, max_age_s: float = 12 * 3600.0, max_sessions: int = 1000) -> None:
        self._tokens = tokens
        self.max_age_s = max_age_s
        self._max = max_sessions
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()

    def open(self, token: str) -> tuple[str, Session, Principal] | None:
        """A new session for ``token`` (its id, the session and who it is), or None if the token is unknown."""
        digest = hash_token(token)
        principal = self._tokens.authenticate_hash(digest)
        if principal is None:
            return None
        session_id = secrets.token_urlsafe(32)
        session = Session(digest, secrets.token_urlsafe(32), time.monotonic() + self.max_age_s)
        with self._lock:
            now = time.monotonic()
            for old in [k for k, s in self._sessions.items() if s.expires <= now]:
                del self._sessions[old]
            if len(self._sessions) >= self._max:  # the oldest goes first
                del self._sessions[min(self._sessions, key=lambda k: self._sessions[k].expires)]
            self._sessions[session_id] = session
        return session_id, session, principal

    def lookup(self, session_id: str) -> tuple[Session, Principal] | None:
        """The live session of ``session_id`` and who it is, or None (unknown, expired, or its token revoked)."""
        if not session_id or len(session_id) > 128:
            return None
        with self._lock:
            session = self._sessions.get(session_id)
            if session is not None and session.expires <= time.monotonic():
                del self._sessions[session_id]
                session = None
        if session is None:
            return None
        principal = self._tokens.authenticate_hash(session.token_sha256)
        return (session, principal) if principal is not None else None

    def close(self, session_id: str) -> None:
        """Sign out: forget the session."""
        with self._lock:
            self._sessions.pop(session_id, None)


def csrf_ok(session: Session, sent: str | None) -> bool:
    """Whether ``sent`` is the session's CSRF token (constant-time)."""
    return sent is not None and hmac.compare_digest(sent.encode(), session.csrf.encode())
