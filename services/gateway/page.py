"""The session page at ``GET /``: a small HTML page with plain JavaScript (``static/``, mounted at ``/static`` by
``create_app``), no build step.

It talks to the same HTTP API as any client (``/sessions``), sending the bearer token the user enters, and
links the live view in Foxglove when the gateway runs one (``GET /live``).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from .deps import Settings

STATIC = Path(__file__).parent / "static"

router = APIRouter()


class LiveInfo(BaseModel):
    """Where the Foxglove live view listens (the page builds ``ws://<page host>:<port>`` from it, or on TLS
    ``wss://<page host>:<port>/?token=<the token entered>``)."""

    foxglove_port: int | None = Field(None, description="the Foxglove WebSocket port; null when it is off")
    tls: bool = Field(False, description="the live view is on TLS (wss://) and needs ?token= (a fleet's keys)")


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    """The session page."""
    return FileResponse(STATIC / "index.html", media_type="text/html")


@router.get("/live", response_model=LiveInfo)
def live(settings: Settings) -> LiveInfo:
    """The live view's Foxglove WebSocket port, and whether it is on TLS with a token."""
    return LiveInfo(foxglove_port=settings.foxglove_port, tls=settings.tls_keys is not None)
