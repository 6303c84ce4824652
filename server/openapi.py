"""The OpenAPI schema as clients see it: every error answer documented with its real body.

FastAPI documents its own ``HTTPValidationError`` for 422, but this server answers every error with
:class:`~voxfusion.proto.schemas.ErrorOut` (``{"detail", "field"}``: :mod:`.errors`), and it lists only the
statuses a route declares. :func:`document_errors` post-processes the generated schema once:

* every ``422`` answer is ``ErrorOut`` (FastAPI's validation models are dropped from the components);
* every operation documents the statuses any request can get whatever the route: ``500`` (a bug: JSON too),
  ``413`` for requests with a body (the size limit is checked before the route), ``422`` for operations with
  parameters or a body;
* operations on one session (``{session_id}`` in the path) document ``401`` / ``403`` (token), ``404``
  (unknown id), ``409`` (its state), ``429`` (its queue) and ``503`` (its worker restarting, or no slot to
  resume it in).

``tests/server/test_openapi.py`` checks the result with schemathesis against a live server: no status code
the schema does not list, and no 5xx.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

__all__ = ["document_errors"]

_ERROR_REF = {"$ref": "#/components/schemas/ErrorOut"}
_DESCRIPTIONS = {
    "401": "No token or API key was sent.",
    "403": "Wrong token or API key.",
    "404": "Unknown session (or a malformed id).",
    "409": "The session's state does not allow it (finished, failed, nothing mapped yet).",
    "413": "Request body or image larger than the server's limits.",
    "422": "A parameter, field or frame value is invalid; ``field`` names it.",
    "429": "Too many frames waiting for this session's engine, or sessions for this client (``Retry-After``).",
    "500": "A bug in the server (the log has the details).",
    "503": "No free session slot, or the session's worker is restarting (``Retry-After``).",
}
_SESSION_STATUSES = ("401", "403", "404", "409", "429", "503")


def _error_response(status: str) -> dict[str, Any]:
    return {"description": _DESCRIPTIONS.get(status, "Error."), "content": {"application/json": {"schema": _ERROR_REF}}}


def _document_operation(path: str, method: str, op: dict[str, Any]) -> None:
    responses = op.setdefault("responses", {})
    statuses = {"500"}
    if op.get("parameters") or op.get("requestBody"):
        statuses.add("422")
    if op.get("requestBody") or method in ("post", "put", "patch"):
        statuses.add("413")
    if "{session_id}" in path:
        statuses.update(_SESSION_STATUSES)
    for status in statuses:
        current = responses.get(status)
        if current is None:
            responses[status] = _error_response(status)
        else:  # declared by the route: make sure the body is ours (FastAPI's 422 is not)
            current["content"] = {"application/json": {"schema": _ERROR_REF}}
            current.setdefault("description", _DESCRIPTIONS.get(status, "Error."))
    for status, response in responses.items():
        if status.startswith(("4", "5")):
            response["content"] = {"application/json": {"schema": _ERROR_REF}}


def document_errors(app: FastAPI) -> None:
    """Make ``app.openapi()`` document every error answer as ``ErrorOut`` (see the module docstring)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description,
                                 routes=app.routes)
            for path, item in schema.get("paths", {}).items():
                for method, op in item.items():
                    if isinstance(op, dict) and "responses" in op:
                        _document_operation(path, method, op)
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            components.pop("HTTPValidationError", None)
            components.pop("ValidationError", None)
            if "ErrorOut" not in components:
                from voxfusion.proto.schemas import ErrorOut

                components["ErrorOut"] = ErrorOut.model_json_schema(ref_template="#/components/schemas/{model}")
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
