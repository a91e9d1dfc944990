"""``GET /metrics`` in the Prometheus text format."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.api.deps import get_metrics

router = APIRouter(tags=["metrics"])


@router.get(
    "/metrics", response_class=Response, summary="Prometheus metrics",
    responses={200: {"description": "The Prometheus text exposition format, of the version its Content-Type names.",
                     "content": {"text/plain": {"schema": {"type": "string"}}}}},
)
async def metrics(request: Request) -> Response:
    return Response(generate_latest(get_metrics(request).registry), media_type=CONTENT_TYPE_LATEST)
