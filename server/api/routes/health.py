"""Liveness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from voxfusion.proto.api_extra import HealthOut

from ...metrics import CONTENT_TYPE, render_metrics
from ..deps import ApiKeyDep, ManagerDep

__all__ = ["router"]

router = APIRouter(tags=["server"])


@router.get("/healthz", response_model=HealthOut)
def healthz(manager: ManagerDep) -> HealthOut:
    """The server is up: version, device, open sessions."""
    return manager.health()


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(manager: ManagerDep, request: Request, _: ApiKeyDep) -> PlainTextResponse:
    """Prometheus text format (requires the server API key when one is configured)."""
    return PlainTextResponse(render_metrics(manager, request.app.state.http_stats), media_type=CONTENT_TYPE)
