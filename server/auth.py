"""Session ids and access tokens.

* Session ids are server-generated (``uuid4().hex``: 32 lower-case hex digits) and every id a client
  sends is checked against :data:`SESSION_ID_RE` before it is used for anything, so no client string
  ever becomes part of a path.
* Each session has a bearer token (``secrets.token_urlsafe(32)``), shown once at creation; only its
  SHA-256 is stored, and tokens are compared in constant time (``hmac.compare_digest``).
* The optional server API key (``VOXFUSION_API_KEY``) is compared the same way.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import re
import secrets
import uuid

from .errors import ForbiddenError, SessionNotFoundError, UnauthorizedError

__all__ = [
    "RedactTokens",
    "SESSION_ID_RE",
    "new_session_id",
    "check_session_id",
    "new_token",
    "hash_token",
    "verify_token",
    "verify_api_key",
    "bearer_token",
]

SESSION_ID_RE = re.compile(r"^[0-9a-f]{32}$")
"""What a session id looks like (``uuid4().hex``)."""


def new_session_id() -> str:
    """A fresh session id (32 hex digits)."""
    return uuid.uuid4().hex


def check_session_id(session_id: str) -> str:
    """Return ``session_id`` if it has the id format, else raise :class:`SessionNotFoundError` (404)."""
    if not isinstance(session_id, str) or not SESSION_ID_RE.fullmatch(session_id):
        raise SessionNotFoundError(str(session_id))
    return session_id


def new_token() -> str:
    """A fresh bearer token (43 URL-safe characters, 256 random bits)."""
    return secrets.token_urlsafe(32)


def hash_token(token: str) -> str:
    """SHA-256 hex digest of ``token`` (what the database stores)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def verify_token(token: str | None, stored_hash: str) -> None:
    """Raise :class:`UnauthorizedError` when ``token`` is missing and :class:`ForbiddenError` when it is wrong."""
    if not token:
        raise UnauthorizedError("this session's token is required: send 'Authorization: Bearer <token>'")
    if not hmac.compare_digest(hash_token(token), stored_hash):
        raise ForbiddenError("wrong token for this session", "Authorization")


def verify_api_key(sent: str | None, api_key: str | None) -> None:
    """Check the server API key (nothing to check when the server has none)."""
    if api_key is None:
        return
    if not sent:
        raise UnauthorizedError("this server requires its API key: send 'X-API-Key: <key>' or "
                           "'Authorization: Bearer <key>'", "X-API-Key")
    if not hmac.compare_digest(sent.encode("utf-8"), api_key.encode("utf-8")):
        raise ForbiddenError("wrong API key", "X-API-Key")


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header value, or ``None``."""
    if not authorization:
        return None
    scheme, _, value = authorization.strip().partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        return None
    return value.strip()


class RedactTokens(logging.Filter):
    """A logging filter that hides ``token=...`` query values (the viewer link and the pose WebSocket carry
    the session token there) in log records, e.g. uvicorn's access log: ``token=***``."""

    _TOKEN = re.compile(r"(token=)[^&\s\"']+")

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(self._TOKEN.sub(r"\1***", a) if isinstance(a, str) else a for a in record.args)
        if isinstance(record.msg, str):
            record.msg = self._TOKEN.sub(r"\1***", record.msg)
        return True
