"""The gateway's FastAPI app: ``create_app`` assembles it from the settings, the bus, the middleware, the error
handlers and the routers.

The routes live in one ``APIRouter`` per resource: ``routes/sessions.py`` (``POST /sessions`` and the rest of
``/sessions``), ``routes/maps.py`` (``/maps``), ``routes/audit.py`` (``/audit``), ``routes/health.py``
(``/healthz``) and ``page.py`` (``/``, ``/live``). They reach the shared state (settings,
:class:`~.bus.GatewayBus`, session table) through the dependencies of ``deps.py``, which read ``app.state``.
"""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from twohr.errors import validation_problems

from . import page
from .audit import AuditLog, KeysWatch
from .bus import GatewayBus
from .ownership import Grants
from .routes import audit, health, maps, sessions
from .sessions import SessionTable
from .settings import GatewaySettings
from .tokens import Tokens


@asynccontextmanager
async def lifespan(app: FastAPI):
    """The bus is up while the app serves, and the keys folder is watched for the audit trail."""
    app.state.bus.start()
    app.state.keys_watch.start()
    yield
    app.state.keys_watch.close()
    app.state.bus.close()


async def limit_body(request: Request, call_next):
    """413 for a body over the limit (a map upload's, or any other request's); a POST body without a JSON content
    type is read as JSON."""
    settings: GatewaySettings = request.app.state.settings
    size = request.headers.get("content-length")
    limit = settings.max_map_bytes if request.url.path == "/maps" else settings.max_request_bytes
    if size is not None and (not size.isdigit() or int(size) > limit):
        return JSONResponse({"detail": f"request body over {limit} bytes"}, status_code=413)
    content_type = request.headers.get("content-type", "")
    if request.method == "POST" and request.url.path != "/maps" and (not content_type or content_type.startswith(
            ("application/x-www-form-urlencoded", "text/plain"))):
        # every body here is JSON: `curl -d '{...}'` (form-encoded by default) works as it reads
        request.scope["headers"] = [(k, v) for k, v in request.scope["headers"] if k != b"content-type"] + [
            (b"content-type", b"application/json")]
    return await call_next(request)


async def validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """A request that does not validate: 422 with one line naming the fields."""
    problems = validation_problems(exc, skip=("body",))
    return JSONResponse({"detail": f"invalid request: {problems}"[:2000]}, status_code=422)


def create_app(settings: GatewaySettings) -> FastAPI:
    """The HTTP API over one :class:`GatewayBus` and its session table."""
    app = FastAPI(title="twohr gateway", version="1", lifespan=lifespan,
                  description="Start, follow and stop twohr SLAM sessions. Poses stream on Zenoh at "
                  "twohr/<robot>/pose.")
    app.state.settings = settings
    app.state.table = SessionTable()
    audit_log = AuditLog(settings.audit_file())
    app.state.keys_watch = KeysWatch(audit_log, settings.robot_tokens, settings.grants_file())
    app.state.tokens = Tokens(settings.api_token, settings.robot_tokens)
    app.state.bus = GatewayBus(settings, app.state.table, audit_log,
                               Grants(settings.grants_file(), on_change=app.state.keys_watch.poll), app.state.tokens)
    app.middleware("http")(limit_body)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.include_router(page.router)
    app.mount("/static", StaticFiles(directory=page.STATIC), name="static")
    app.include_router(health.router)
    app.include_router(sessions.router)
    app.include_router(maps.router)
    app.include_router(audit.router)
    return app
