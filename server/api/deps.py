"""Typed dependencies of the routes: the manager, the server API key, and an authorised session id.

``SessionIdDep`` checks, in order: the id's format and existence (404), then the session's bearer token
(401 missing, 403 wrong). ``ApiKeyDep`` checks the optional server API key (``X-API-Key`` or
``Authorization: Bearer``). ``AnonymousClientDep`` names the client that the per-client session limit
applies to (``max_sessions_per_client``).
"""

from __future__ import annotations

import ipaddress
from typing import Annotated

from fastapi import Depends, Header, Path, Request

from ..auth import bearer_token
from ..manager import SessionManager
from ..settings import ServerSettings

__all__ = ["get_manager", "get_settings", "anonymous_client", "ManagerDep", "SettingsDep", "ApiKeyDep",
           "AnonymousClientDep", "SessionIdDep"]


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


def client_key(host: str) -> str | None:
    """What the per-client limit counts sessions by, for a client at ``host``: ``None`` on loopback (not
    limited), an IPv6 address's /64 network (one host usually has a whole /64), else the address itself."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host  # not an address (e.g. a proxy's unparsable X-Forwarded-For): counted as given
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    if ip.is_loopback:
        return None
    if isinstance(ip, ipaddress.IPv6Address):
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


def anonymous_client(request: Request, settings: SettingsDep) -> str | None:
    """The client a session is created for when the per-client limit applies: the server has no API key
    and the client is beyond loopback. ``None`` otherwise (API key holders, loopback, Unix sockets).

    The address is the TCP peer's, or the one uvicorn took from ``X-Forwarded-For`` when the peer is a
    proxy it trusts (environment ``FORWARDED_ALLOW_IPS``, default 127.0.0.1)."""
    if settings.api_key is not None or request.client is None or not request.client.host:
        return None
    return client_key(request.client.host)


AnonymousClientDep = Annotated[str | None, Depends(anonymous_client)]


def authorised_session(
    manager: ManagerDep,
    session_id: Annotated[str, Path(description="Session id (32 hex digits) from POST /sessions.")],
    authorization: Annotated[str | None, Header(description="'Bearer <session token>'")] = None,
) -> str:
    """The session id, once it exists and the request carries its token."""
    manager.check_token(session_id, bearer_token(authorization))
    return session_id


SessionIdDep = Annotated[str, Depends(authorised_session)]
