"""The gateway's HTTP routes: FastAPI control of sessions over the Zenoh bus.

``POST /sessions`` validates the request (the sequence must lie under a configured data root,
the config overrides and model names must validate) and asks the :class:`~.bus.GatewayBus` to
publish a ``start`` control message; the source, the cores and the recorder take it from there.
The bus side follows each session's poses, status and services (``bus.py``); the routes serve its
state, trajectory, ATE and recording, and the session page (``page.py``).
"""

from __future__ import annotations

import asyncio
import logging
import os
import secrets
import time
import uuid
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import Depends, FastAPI, HTTPException, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse
from pydantic import BaseModel, Field

from twohr.bus import BusConfig, query_health
from twohr.config import PipelineConfig, load_config
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError, validation_problems
from twohr.keys import PIPELINE_SERVICES
from twohr.mapfile import MapEntry, MapFileError, MapStore, read_map
from twohr.mcapfile import is_finalised, partial_marker
from twohr.models import get_spec
from twohr.paths import resolve_under_roots
from twohr.trajectory import tum_text

from .bus import GatewayBus
from .page import mount_page
from .sessions import ACTIVE, MapRequest, PoseOut, Session, SessionInfo, SessionRequest, SessionTable

log = logging.getLogger("twohr.gateway")


class Problem(BaseModel):
    """Every error reply: one line saying what is wrong and how to fix it."""

    detail: str


# the content type is spelled out: with a model, FastAPI would document a text route's errors as text
ERRORS = {code: {"description": text, "content": {"application/json": {"schema": Problem.model_json_schema()}}}
          for code, text in {
    400: "the request body is not valid JSON text", 401: "missing or wrong API token", 404: "no such session",
    409: "conflict with the session's state",
    413: "request body too large", 422: "invalid request: the detail names the field",
    503: "a service the session needs is not running"}.items()}


def errors(*codes: int) -> dict:
    """The OpenAPI ``responses`` of a route that can answer ``codes``."""
    return {code: ERRORS[code] for code in codes}


class GatewaySettings(BaseModel):
    """Gateway configuration (command-line flags of ``python -m twohr_services.gateway``)."""

    data_roots: list[Path] = Field(default_factory=lambda: [Path("data")])
    recordings: Path = Path("recordings")
    api_token: str | None = Field(default_factory=lambda: os.environ.get("TWOHR_API_TOKEN") or None,
                                  description="if set, requests need 'Authorization: Bearer <token>'")
    bus: BusConfig = Field(default_factory=BusConfig)
    idle_timeout: float = Field(15.0, gt=0, description="a session whose source is done and that gets no pose "
                                "for this long is finished")
    start_timeout: float = Field(180.0, gt=0, description="a session with no pose this long after its start fails")
    stall_timeout: float = Field(45.0, gt=0, description="a running session with no pose for this long fails")
    refine_timeout: float = Field(30.0, gt=0, description="after a session ends, how long its refined trajectory "
                                  "(from the tracker) is waited for before the online poses are served instead")
    keep_ended: int = Field(200, ge=1, description="ended sessions kept in the table (the oldest are forgotten)")
    max_request_bytes: int = Field(256 * 1024, ge=1024, description="larger request bodies get 413")
    foxglove_host: str = Field("127.0.0.1", description="interface of the Foxglove live view")
    foxglove_port: int | None = Field(None, ge=0, le=65535, description="Foxglove live view port; None = off")
    maps: Path | None = Field(None, description="the map store's folder (served on twohr/maps/<name> and /maps); "
                              "None = no map store")
    max_map_bytes: int = Field(512 * 1024 * 1024, ge=1024, description="larger map uploads get 413")


def validate_models(config: PipelineConfig) -> None:
    """Every model the config names must be registered, and of the right kind."""
    if config.detector.features != "orb":
        get_spec(config.detector.model, "r2d2")
    if config.yolo.enabled:
        spec = get_spec(config.yolo.model)
        if spec.kind not in ("yolov8", "yolov5"):
            raise TwohrError(f"yolo.model {config.yolo.model!r} is a {spec.kind} model, not a YOLO detector")
    if config.matcher.method == "siamese":
        get_spec(config.matcher.model, "siamese")


def create_app(settings: GatewaySettings) -> FastAPI:
    """The HTTP routes over one :class:`GatewayBus` and its session table."""
    table = SessionTable()
    bus = GatewayBus(settings, table)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        bus.start()
        yield
        bus.close()

    app = FastAPI(title="twohr gateway", version="1", lifespan=lifespan,
                  description="Start, follow and stop twohr SLAM sessions. Poses stream on Zenoh at "
                  "twohr/<robot>/pose.")

    mount_page(app, settings.foxglove_port)

    def require_token(request: Request) -> None:
        if settings.api_token is None:
            return
        supplied = request.headers.get("authorization", "").removeprefix("Bearer ").strip()
        # compared as bytes: a header with non-ASCII characters is simply a wrong token
        if not secrets.compare_digest(supplied.encode("utf-8", "surrogateescape"), settings.api_token.encode()):
            raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing or wrong API token (Authorization: Bearer …)")

    @app.middleware("http")
    async def limit_body(request: Request, call_next):
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

    @app.exception_handler(RequestValidationError)
    async def validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = validation_problems(exc, skip=("body",))
        return JSONResponse({"detail": f"invalid request: {problems}"[:2000]}, status_code=422)

    def info(session: Session) -> SessionInfo:
        latest = session.poses.latest
        recording = settings.recordings / f"{session.id}.mcap"
        return SessionInfo(
            id=session.id, robot_id=session.request.robot_id, source=session.request.source,
            sequence=session.request.sequence,
            state=session.state, detail=session.detail, created=session.created,
            frames_total=session.frames_total, frames_sent=session.frames_sent, frames=len(session.poses),
            frames_dropped=max(0, session.frames_sent - session.poses.distinct_frames() - session.unposed)
            if session.frames_sent is not None and (session.state not in ACTIVE or session.request.source == "camera")
            else None,
            fps=round(session.fps(), 3),
            latest_pose=PoseOut(frame_index=latest.frame_index, stamp=latest.stamp, position=latest.position,
                                orientation=latest.orientation, status=latest.status) if latest else None,
            ate_rmse=session.ate_rmse, ate_rmse_online=session.ate_rmse_online,
            trajectory="online" if session.refined is None else "refined", corrections=session.corrections,
            health=session.health, health_detail=session.health_detail,
            record=session.request.record,
            recording=f"/sessions/{session.id}/recording" if recording.is_file() else None,
            map=session.request.map, start=session.request.start,
        )

    def lookup(session_id: str) -> Session:
        session = table.get(session_id)
        if session is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no session {session_id}")
        return session

    @app.get("/healthz")
    def healthz() -> dict:
        """Gateway liveness plus each service's counters (null when a service does not answer)."""
        zsession = bus.session
        services = {name: query_health(zsession, name, timeout=0.5) for name in PIPELINE_SERVICES} if zsession else {}
        return {"status": "ok", "services": services}

    @app.post("/sessions", status_code=201, response_model=SessionInfo, dependencies=[Depends(require_token)],
              responses=errors(400, 401, 409, 413, 422, 503))
    def create_session(request: SessionRequest) -> SessionInfo:
        """Start a session on a sequence under the data roots. 409 if the robot already runs one, 503 if a
        service is not running."""
        try:
            config = load_config(None, request.config)
            validate_models(config)
            folder = None
            if request.source == "sequence":
                folder = resolve_under_roots(request.sequence, settings.data_roots)
                if request.start >= len(RGBDSequence(folder, camera=config.camera)):
                    raise TwohrError(f"start: frame {request.start} is past the sequence's end")
            if request.map is not None:
                check_map(request.map, config)
        except TwohrError as exc:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)[:2000]) from None
        except OSError as exc:  # e.g. a name too long for the file system
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"sequence: {exc.strerror}") from None
        missing = bus.missing_services()
        if missing:
            raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"services not running: {', '.join(missing)}")
        if table.active_for_robot(request.robot_id):
            raise HTTPException(status.HTTP_409_CONFLICT, f"robot {request.robot_id} already runs a session")
        session = Session(id=uuid.uuid4().hex[:12], request=request, folder=folder)
        table.add(session)
        bus.send_control(session, "start", config)
        return info(session)

    def store() -> MapStore:
        if settings.maps is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, "this gateway has no map store (twohr up --maps DIR)")
        return MapStore(settings.maps)

    def check_map(wanted: MapRequest, config: PipelineConfig) -> None:
        """A session's map must be usable before the session starts: a store for it, and for localize and extend
        a readable map built with the session's detector model (422 otherwise, one line)."""
        if settings.maps is None:
            raise TwohrError("map: this gateway has no map store (start it with twohr up --maps DIR)")
        path = MapStore(settings.maps).path(wanted.name)  # a name the store can keep, in every mode
        if wanted.mode == "build":
            return
        if not path.is_file():
            raise TwohrError(f"map: no map named {wanted.name!r} in the map store (GET /maps lists them)")
        read_map(path, detector=config.detector)

    @app.get("/maps", response_model=list[MapEntry], dependencies=[Depends(require_token)], responses=errors(401, 404))
    def list_maps() -> list[MapEntry]:
        """The maps in the store (the latest version of each); an unreadable file is left out and logged."""
        good, bad = store().entries()
        for name, why in bad.items():
            log.warning("map %s is not readable: %s", name, why)
        return good

    @app.get("/maps/{name}", dependencies=[Depends(require_token)],
             responses={200: {"content": {"application/octet-stream": {}}, "description": "the map file"},
                        **errors(401, 404)})
    def download_map(name: str) -> FileResponse:
        """A map's file (its latest version)."""
        try:
            path = store().path(name)
        except MapFileError as exc:
            raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
        if not path.is_file():
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no map named {name!r}")
        return FileResponse(path, media_type="application/octet-stream", filename=path.name)

    @app.post("/maps", status_code=201, response_model=MapEntry, dependencies=[Depends(require_token)],
              responses=errors(401, 404, 413, 422),
              openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": {
                  "schema": {"type": "string", "format": "binary"}}}}})
    async def upload_map(request: Request, name: str | None = None) -> MapEntry:
        """Keep an uploaded map file (the body), checked through first, under its name (``name``, if given, must be
        the one in its header); a map already under that name is kept as an earlier version."""
        maps = store()
        chunks, size = [], 0
        async for chunk in request.stream():  # a chunked upload has no Content-Length for the middleware to check
            size += len(chunk)
            if size > settings.max_map_bytes:
                raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"map over {settings.max_map_bytes} bytes")
            chunks.append(chunk)
        try:
            return await run_in_threadpool(maps.save, b"".join(chunks), name)  # checks and fsyncs: off the loop
        except MapFileError as exc:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)[:2000]) from None

    @app.delete("/maps/{name}", status_code=204, dependencies=[Depends(require_token)], responses=errors(401, 404))
    def delete_map(name: str) -> None:
        """Remove a map and its earlier versions."""
        try:
            removed = store().delete(name)
        except MapFileError as exc:
            raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
        if not removed:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no map named {name!r}")

    @app.get("/sessions", response_model=list[SessionInfo], dependencies=[Depends(require_token)],
             responses=errors(401))
    def list_sessions() -> list[SessionInfo]:
        return [info(s) for s in list(table.sessions.values())]

    @app.get("/sessions/{session_id}", response_model=SessionInfo, dependencies=[Depends(require_token)],
             responses=errors(401, 404))
    def get_session(session_id: str) -> SessionInfo:
        return info(lookup(session_id))

    @app.delete("/sessions/{session_id}", response_model=SessionInfo, dependencies=[Depends(require_token)],
                responses=errors(401, 404))
    def stop_session(session_id: str) -> SessionInfo:
        """Stop a session (its robot is free at once); an ended session is returned unchanged."""
        session = lookup(session_id)
        if session.state in ACTIVE:
            session.state = "stopped"
            bus.send_control(session, "stop")
        return info(session)

    @app.get("/sessions/{session_id}/trajectory", response_class=PlainTextResponse,
             dependencies=[Depends(require_token)], responses=errors(401, 404, 422))
    async def trajectory(session_id: str, online: bool = False) -> PlainTextResponse:
        """The session's trajectory in TUM format (camera-to-world). Once the session has ended: the refined
        trajectory the tracker sends then (final bundle adjustment, re-anchoring, smoothing), waited for a few
        seconds if it is not in yet; while it runs, or with ``online=true``: the poses as published. The header
        ``X-Twohr-Trajectory`` says which (``refined`` or ``online``)."""
        session = lookup(session_id)
        while not online and session.refined is None and session.refined_due is not None and (
                time.time() < session.refined_due) and "tracker" in bus.alive:
            await asyncio.sleep(0.1)
        refined = None if online else session.refined
        trajectory = session.trajectory() if refined is None else refined
        return PlainTextResponse(tum_text(trajectory),
                                 headers={"X-Twohr-Trajectory": "online" if refined is None else "refined"})

    @app.get("/sessions/{session_id}/recording", dependencies=[Depends(require_token)],
             responses={200: {"content": {"application/octet-stream": {}},
                              "description": "the MCAP file; header X-Twohr-Recording: partial when the recorder "
                              "died and its readable prefix was re-indexed"}, **errors(401, 404, 409)})
    async def recording(session_id: str) -> FileResponse:
        """The session's MCAP file, once the session has ended."""
        session = lookup(session_id)
        path = settings.recordings / f"{session.id}.mcap"
        if not session.request.record:
            raise HTTPException(status.HTTP_404_NOT_FOUND, "this session was not recorded")
        if session.state in ACTIVE:
            raise HTTPException(status.HTTP_409_CONFLICT, "the recording is finalised when the session ends")
        started = time.monotonic()
        # the recorder finalises the file once the session's refined path is in (or no longer expected): a file it
        # has opened is waited for that long, a file that is not there at all 10 s
        while not is_finalised(path) and time.monotonic() - started < (
                10 + settings.refine_timeout if path.is_file() else 10):
            await asyncio.sleep(0.1)
        if not path.is_file():
            raise HTTPException(status.HTTP_404_NOT_FOUND, "no recording found (is the recorder running?)")
        if not is_finalised(path):
            raise HTTPException(status.HTTP_409_CONFLICT, "the recording is still being finalised; try again")
        partial = partial_marker(path).is_file()
        return FileResponse(path, media_type="application/octet-stream", filename=path.name,
                            headers={"X-Twohr-Recording": "partial" if partial else "complete"})

    return app
