"""The session page at ``GET /``: a small HTML page with plain JavaScript (``static/``, mounted at ``/static`` by
``create_app``), no build step.

It talks to the same HTTP API as any client (``/sessions``), sending the bearer token the user enters, and
links the live view in Foxglove when the gateway runs one (``GET /live``): on a fleet's keys with the view token
``GET /live`` gives for the token entered, never the API token itself (the link goes to app.foxglove.dev).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from .deps import Settings, errors, require_token, token_check
from .tokens import Tokens, view_token

STATIC = Path(__file__).parent / "static"

router = APIRouter()


class LiveInfo(BaseModel):
    """Where the Foxglove live view listens (the page builds ``ws://<page host>:<port>`` from it, or on TLS
    ``wss://<page host>:<port>/?token=<view token>``)."""

    foxglove_port: int | None = Field(None, description="the Foxglove WebSocket port; null when it is off")
    tls: bool = Field(False, description="the live view is on TLS (wss://) and needs ?token= (a fleet's keys)")
    view_token: str | None = Field(None, description="with an API token (Authorization: Bearer) on a live view on "
                                   "TLS: the token to put in the live view's URL. It opens the live view with the "
                                   "same sight as the API token and is refused by the HTTP API, so a Foxglove URL "
                                   "never carries the API token")


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    """The session page."""
    return FileResponse(STATIC / "index.html", media_type="text/html")


@router.get("/live", response_model=LiveInfo, response_model_exclude_unset=True, responses=errors(401))
async def live(request: Request, settings: Settings, check: Annotated[Tokens, Depends(token_check)]) -> LiveInfo:
    """The live view's Foxglove WebSocket port, and whether it is on TLS with a token; to a request with an API
    token (401 for a wrong one, a view token included), the view token that goes into the live view's URL in its
    place."""
    fields = {"foxglove_port": settings.foxglove_port, "tls": settings.tls_keys is not None}
    if "authorization" in request.headers:
        await require_token(request, check)
        if fields["foxglove_port"] and fields["tls"] and check.required:
            fields["view_token"] = view_token(request.headers["authorization"].removeprefix("Bearer ").strip())
    return LiveInfo(**fields)
