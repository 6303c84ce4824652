"""Client-side errors: what the server refused (with its HTTP-equivalent status) and what never arrived."""

from __future__ import annotations

import json
from typing import Any

from voxfusion.core.errors import VoxFusionError

__all__ = ["ClientError", "ServerError", "TransportError", "server_error_from_body"]


class ClientError(VoxFusionError):
    """Base of every error the client SDK raises."""


class ServerError(ClientError):
    """The server refused a request.

    Attributes:
        status: HTTP status (over zenoh: the status the HTTP API would have answered), e.g. 400, 403, 404,
            409 (finished session / nothing to serve yet), 413, 422, 429 (queue full), 503.
        detail: the server's explanation.
        field: the offending input (``"T_world_cam"``, ``"depth"``, ``"crc"``, ``"Authorization"``) or ``None``.
        retry_after_s: the server's ``Retry-After`` (429 / 503), else ``None``.
    """

    def __init__(self, status: int, detail: str, field: str | None = None, retry_after_s: float | None = None) -> None:
        self.status = int(status)
        self.detail = str(detail)
        self.field = field
        self.retry_after_s = retry_after_s
        where = f" [{field}]" if field else ""
        super().__init__(f"server answered {self.status}{where}: {self.detail}")


class TransportError(ClientError):
    """The server could not be reached, or did not answer in time."""


def server_error_from_body(status: int, body: bytes | str | dict[str, Any] | None) -> ServerError:
    """A :class:`ServerError` from an ``ErrorOut`` body (``{"detail", "field"}``, optionally ``"status"``);
    a body that is not such JSON becomes the detail text."""
    data: Any = body
    if isinstance(body, (bytes, bytearray)):
        body = bytes(body).decode("utf-8", errors="replace")
    if isinstance(body, str):
        try:
            data = json.loads(body)
        except ValueError:
            data = None
    if isinstance(data, dict) and "detail" in data:
        detail = data["detail"]
        if not isinstance(detail, str):  # FastAPI's own 422 bodies carry a list here
            detail = json.dumps(detail)
        field = data.get("field")
        return ServerError(int(data.get("status", status)), detail, field if isinstance(field, str) else None)
    text = body if isinstance(body, str) and body else f"HTTP {status}"
    return ServerError(status, text[:500])
