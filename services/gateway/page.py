"""The session page at ``GET /``: a small HTML page with plain JavaScript (``static/``), no build step.

It talks to the same HTTP API as any client (``/sessions``), sending the bearer token the user enters, and
links the live view in Foxglove when the gateway runs one (``GET /live``).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

STATIC = Path(__file__).parent / "static"


class LiveInfo(BaseModel):
    """Where the Foxglove live view listens (the page builds ``ws://<page host>:<port>`` from it)."""

    foxglove_port: int | None = Field(None, description="the Foxglove WebSocket port; null when it is off")


def page_router(foxglove_port: int | None) -> APIRouter:
    """``GET /`` (the page), ``GET /live`` and the page's static files under ``/static``."""
    router = APIRouter()

    @router.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html")

    @router.get("/live", response_model=LiveInfo)
    def live() -> LiveInfo:
        """The live view's Foxglove WebSocket port."""
        return LiveInfo(foxglove_port=foxglove_port)

    return router


def mount_page(app, foxglove_port: int | None) -> None:
    """Add the session page to a FastAPI app."""
    app.include_router(page_router(foxglove_port))
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
