"""What the routers share: the gateway's state (set on ``app.state`` by ``create_app``) as FastAPI dependencies,
the API token check, and the error replies the routes document."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from pydantic import BaseModel

from .bus import GatewayBus
from .sessions import SessionTable
from .settings import GatewaySettings
from .tokens import Caller, Tokens


class Problem(BaseModel):
    """Every error reply: one line saying what is wrong and how to fix it."""

    detail: str


# the content type is spelled out: with a model, FastAPI would document a text route's errors as text
ERRORS = {code: {"description": text, "content": {"application/json": {"schema": Problem.model_json_schema()}}}
          for code, text in {
    400: "the request body is not valid JSON text", 401: "missing or wrong API token",
    403: "a robot's token, for another robot's session or the operator's work", 404: "no such session",
    409: "conflict with the session's state",
    413: "request body too large", 422: "invalid request: the detail names the field",
    503: "a service the session needs is not running"}.items()}


def errors(*codes: int) -> dict:
    """The OpenAPI ``responses`` of a route that can answer ``codes``."""
    return {code: ERRORS[code] for code in codes}


# the accessors are coroutines: FastAPI would run plain functions in its thread pool, for an attribute lookup
async def gateway_settings(request: Request) -> GatewaySettings:
    """The gateway's settings."""
    return request.app.state.settings


async def gateway_bus(request: Request) -> GatewayBus:
    """The gateway's side of the Zenoh bus."""
    return request.app.state.bus


async def session_table(request: Request) -> SessionTable:
    """The gateway's sessions."""
    return request.app.state.table


Settings = Annotated[GatewaySettings, Depends(gateway_settings)]
Bus = Annotated[GatewayBus, Depends(gateway_bus)]
Table = Annotated[SessionTable, Depends(session_table)]


async def token_check(request: Request) -> Tokens:
    """The gateway's token check (:class:`~.tokens.Tokens`, the live view's too)."""
    return request.app.state.tokens


async def require_token(request: Request, check: Annotated[Tokens, Depends(token_check)]) -> Caller:
    """401 unless the request carries the operator's API token (when the gateway has one) or, where the gateway
    knows the robots' tokens, a robot's not expired, as ``Authorization: Bearer``; returns who it is. A live view
    token is not one."""
    if not check.required:
        return Caller()
    caller = check.identify(request.headers.get("authorization", "").removeprefix("Bearer ").strip())
    if caller is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing or wrong API token (Authorization: Bearer …)")
    return caller


Who = Annotated[Caller, Depends(require_token)]
