"""The zenoh key space of the VoxFusion server (version 1): one place for the bridge and the clients.

Every key lives under ``voxfusion/@v1/``. ``<id>`` is a session id (server-generated, URL-safe, never a
wildcard); ``<server-id>`` is the server's zenoh id.

==========================================  ==========  ==============================================
key                                         kind        payload
==========================================  ==========  ==============================================
``sessions/create``                         queryable   query: ``SessionCreate`` JSON (may be empty);
                                                        attachment: the server API key (if required);
                                                        reply: ``SessionCreated`` JSON
``sessions/<id>/frames``                    subscriber  one frame message (``proto/README.md``);
                                                        attachment: the session token (UTF-8)
``sessions/<id>/acks``                      publisher   per received frame, in order: ``FrameAck`` JSON
``sessions/<id>/poses``                     publisher   every tracked pose: ``PoseOut`` JSON
``sessions/<id>/poses/latest``              queryable   reply: ``PoseOut`` JSON
``sessions/<id>/trajectory``                queryable   ``?format=json`` (``Trajectory`` JSON) or
                                                        ``?format=tum`` (TUM text)
``sessions/<id>/status``                    queryable   reply: ``SessionStatus`` JSON
``sessions/<id>/render``                    queryable   query: ``RenderRequest`` JSON; reply: the depth
                                                        image (``f16`` / ``png16`` as requested), with
                                                        ``RenderMeta`` JSON in the reply attachment
``sessions/<id>/mesh``                      queryable   ``?format=ply|glb|obj``; reply: the mesh file
``sessions/<id>/voxels``                    queryable   ``?format=npz|ply``; reply: the voxel file
``sessions/<id>/finish``                    queryable   reply: ``SessionStatus`` JSON once finished
``servers/<server-id>``                     liveliness  one token per running server
``sessions/<id>``                           liveliness  one token per live (created / running) session
==========================================  ==========  ==============================================

Every query to a session key carries the session token as its attachment (UTF-8). Errors come back as
zenoh error replies whose payload is ``ErrorOut`` JSON plus the HTTP-equivalent ``status``:
``{"status": 403, "detail": "...", "field": "token"}``.
"""

from __future__ import annotations

__all__ = [
    "PREFIX",
    "CREATE_KEY",
    "SERVERS_LIVELINESS",
    "SESSIONS_LIVELINESS",
    "SESSION_VERBS",
    "QUERY_VERBS",
    "session_key",
    "server_liveliness_key",
    "session_liveliness_key",
    "parse_session_key",
    "check_session_id",
]

PREFIX = "voxfusion/@v1"
"""Root of every key (``@v1``: a verbatim chunk, so wildcards never match across versions)."""
CREATE_KEY = f"{PREFIX}/sessions/create"
"""Queryable creating a session."""
SERVERS_LIVELINESS = f"{PREFIX}/servers/*"
"""Liveliness key expression matching every server's token."""
SESSIONS_LIVELINESS = f"{PREFIX}/sessions/*"
"""Liveliness key expression matching every live session's token."""

SESSION_VERBS = ("frames", "acks", "poses", "poses/latest", "trajectory", "status", "render", "mesh", "voxels",
                 "finish")
"""Every key under ``sessions/<id>/``."""
QUERY_VERBS = ("poses/latest", "trajectory", "status", "render", "mesh", "voxels", "finish")
"""The keys under ``sessions/<id>/`` served by queryables."""

_FORBIDDEN_ID_CHARS = set("/*$?#@ ")


def check_session_id(session_id: str) -> str:
    """Return ``session_id`` if it can be one chunk of a key (non-empty, no ``/ * $ ? # @`` or space).

    Raises:
        ValueError: it cannot.
    """
    if not isinstance(session_id, str) or not session_id or session_id == "create" \
            or any(c in _FORBIDDEN_ID_CHARS for c in session_id):
        raise ValueError(f"session id {session_id!r} cannot be a zenoh key chunk")
    return session_id


def session_key(session_id: str, verb: str) -> str:
    """``voxfusion/@v1/sessions/<id>/<verb>``; ``verb`` is one of :data:`SESSION_VERBS`."""
    if verb not in SESSION_VERBS:
        raise ValueError(f"unknown session key {verb!r}; known: {', '.join(SESSION_VERBS)}")
    return f"{PREFIX}/sessions/{check_session_id(session_id)}/{verb}"


def server_liveliness_key(server_id: str) -> str:
    """``voxfusion/@v1/servers/<server-id>``."""
    return f"{PREFIX}/servers/{check_session_id(server_id)}"


def session_liveliness_key(session_id: str) -> str:
    """``voxfusion/@v1/sessions/<id>`` (a liveliness token, not a data key)."""
    return f"{PREFIX}/sessions/{check_session_id(session_id)}"


def parse_session_key(key: str) -> tuple[str, str]:
    """``(session_id, verb)`` of a concrete key ``voxfusion/@v1/sessions/<id>/<verb>``.

    Raises:
        ValueError: ``key`` is not such a key (another prefix, a wildcard id, an unknown verb).
    """
    head = f"{PREFIX}/sessions/"
    if not key.startswith(head):
        raise ValueError(f"{key!r} is not under {head}")
    session_id, _, verb = key[len(head):].partition("/")
    if verb not in SESSION_VERBS:
        raise ValueError(f"{key!r}: unknown session key {verb!r}")
    return check_session_id(session_id), verb
