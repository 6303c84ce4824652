"""Typed dependencies of the routes: the manager, the server API key, and an authorised session id.

``SessionIdDep`` checks, in order: the id's format and existence (404), then the session's bearer token
(401 missing, 403 wrong). ``ApiKeyDep`` checks the optional server API key (``X-API-Key`` or
``Authorization: Bearer``).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Header, Path, Request

from ..auth import bearer_token
from ..manager import SessionManager
from ..settings import ServerSettings

__all__ = ["get_manager", "get_settings", "ManagerDep", "SettingsDep", "ApiKeyDep", "SessionIdDep"]


def get_manager(request: Request) -> SessionManager:
    """The app's :class:`SessionManager` (built in the lifespan)."""
    return request.app.state.manager


def get_settings(request: Request) -> ServerSettings:
    return request.app.state.settings


ManagerDep = Annotated[SessionManager, Depends(get_manager)]
SettingsDep = Annotated[ServerSettings, Depends(get_settings)]


def require_api_key(manager: ManagerDep,
                    x_api_key: Annotated[str | None, Header(description="Server API key (when configured).")] = None,
                    authorization: Annotated[str | None, Header()] = None) -> None:
    """Check the server API key (nothing to check when the server has none)."""
    manager.check_api_key(x_api_key or bearer_token(authorization))


ApiKeyDep = Annotated[None, Depends(require_api_key)]


def authorised_session(
    manager: ManagerDep,
    session_id: Annotated[str, Path(description="Session id (32 hex digits) from POST /sessions.")],
    authorization: Annotated[str | None, Header(description="'Bearer <session token>'")] = None,
) -> str:
    """The session id, once it exists and the request carries its token."""
    manager.check_token(session_id, bearer_token(authorization))
    return session_id


SessionIdDep = Annotated[str, Depends(authorised_session)]
