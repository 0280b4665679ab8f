"""``/sessions``: start, list, inspect and stop sessions, and serve a session's trajectory and recording.

``POST /sessions`` validates the request (the sequence must lie under a configured data root, the config overrides
and model names must validate, a map must be usable) and asks the :class:`~..bus.GatewayBus` to publish a ``start``
control message; the source, the cores and the recorder take it from there."""

from __future__ import annotations

import asyncio
import threading
import time
import uuid
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException, status
from fastapi.responses import FileResponse, PlainTextResponse

from twohr.config import PipelineConfig, is_table_name, load_config
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError
from twohr.mapfile import MapFileError
from twohr.mapstore import MapStore
from twohr.mcapfile import is_finalised, partial_marker
from twohr.models import get_spec, keyframe_network
from twohr.paths import resolve_under_roots
from twohr.trajectory import tum_text

from ..admission import admit
from ..deps import Bus, Caller, Settings, Table, Who, errors, require_token
from ..ownership import Grants, identity
from ..sessions import ACTIVE, MapRequest, PoseOut, Session, SessionInfo, SessionRequest, SessionTable
from ..settings import GatewaySettings
from ..trackers import PlacementRefused

router = APIRouter(dependencies=[Depends(require_token)])
_admitting = threading.Lock()


def validate_models(config: PipelineConfig) -> None:
    """Every model the config names must be registered, and of the right kind."""
    if config.detector.features != "orb" and config.detector.model != "auto":
        get_spec(keyframe_network(config.detector.model), "r2d2")
    if config.yolo.enabled:
        spec = get_spec(config.yolo.model)
        if spec.kind not in ("yolov8", "yolov5"):
            raise TwohrError(f"yolo.model {config.yolo.model!r} is a {spec.kind} model, not a YOLO detector")
    if config.matcher.method == "siamese":
        get_spec(config.matcher.model, "siamese")


def check_map(wanted: MapRequest, config: PipelineConfig, maps: Path | None) -> None:
    """A session's map must be usable before the session starts: a store for it (``maps``), and for localize and
    extend a stored map whose header reads and names the session's detector model, for share one where the map is
    stored (422 otherwise, one line). The header alone is read: the services that load the map read it whole."""
    if maps is None:
        raise TwohrError("map: this gateway has no map store (start it with twohr up --maps DIR)")
    store = MapStore(maps)
    store.path(wanted.name)  # a name the store can keep, in every mode
    if not wanted.mode.reads_stored:
        return
    header = store.header(wanted.name)
    if header is None:
        if wanted.mode.stored_optional:
            return  # a new shared map: the first robot's frame will be its frame
        raise TwohrError(f"map: no map named {wanted.name!r} in the map store (GET /maps lists them)")
    header.check_built_with(config.detector, str(store.latest_file(wanted.name)))


def check_map_rights(wanted: MapRequest, who: Caller, maps: Path | None, grants: Grants) -> None:
    """403 (one line) when a robot's token builds or extends an existing map that its robot neither owns nor holds
    the operator's grant for; localize, a new map's build and the operator's token pass."""
    if who.robot is None or maps is None or not wanted.mode.needs_rights:
        return
    try:
        owners = MapStore(maps).owners(wanted.name)
    except MapFileError:
        return  # not a name a map can have: checked_start says so (422)
    if owners is not None and not grants.may_change(identity(who.robot), wanted.name, owners):
        raise HTTPException(status.HTTP_403_FORBIDDEN, f"map {wanted.name!r} is owned by {', '.join(owners)}: robot "
                            f"{who.robot} may {wanted.mode.value} it only with the operator's grant (twohr keys grant "
                            f"DIR {who.robot} --map {wanted.name}); localize needs none")


def checked_start(request: SessionRequest, settings: GatewaySettings) -> tuple[PipelineConfig, Path | None]:
    """The config a new session runs with and its sequence's folder (None for a camera); 422 for a request that
    cannot start."""
    try:
        config = load_config(None, request.config)
        validate_models(config)
        table = config.yolo.dynamics_table
        if table is not None and not is_table_name(table):
            raise TwohrError("yolo.dynamics_table: name an installed table (the stack's 'dynamics', or the "
                             "operator's in $TWOHR_DYNAMICS_TABLES), not a path: a session reads no file of its "
                             "caller's choosing")
        folder = None
        if request.source == "sequence":
            folder = resolve_under_roots(request.sequence, settings.data_roots)
            if request.start >= len(RGBDSequence(folder, camera=config.camera)):
                raise TwohrError(f"start: frame {request.start} is past the sequence's end")
        if request.map is not None:
            check_map(request.map, config, settings.maps)
    except TwohrError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)[:2000]) from None
    except OSError as exc:  # e.g. a name too long for the file system
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"sequence: {exc.strerror}") from None
    return config, folder


def session_info(session: Session, recordings: Path) -> SessionInfo:
    """What the API says about a session (``recordings``: the folder its MCAP file would be in)."""
    latest = session.poses.latest
    recording = recordings / f"{session.id}.mcap"
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
        map=session.request.map, start=session.request.start, tracker=session.tracker, moves=session.moves,
        frame_id=latest.frame_id if latest else "", merge=session.merge,
    )


def lookup(table: SessionTable, session_id: str, who: Caller) -> Session:
    """The session ``session_id``; 404 when the table has none, 403 when it is another robot's and ``who`` is a
    robot."""
    session = table.get(session_id)
    if session is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no session {session_id}")
    who.check_robot(session.request.robot_id)
    return session


@router.post("/sessions", status_code=201, response_model=SessionInfo,
             responses=errors(400, 401, 403, 409, 413, 422, 503))
def create_session(request: SessionRequest, settings: Settings, bus: Bus, table: Table, who: Who) -> SessionInfo:
    """Start a session on a sequence under the data roots. 409 if the robot already runs one, 503 if a
    service is not running or the stack is full (``Retry-After``; see ``admission``), 403 for a robot's token and
    another robot's session, or a map it may not build or extend (it neither built it nor holds a grant)."""
    who.check_robot(request.robot_id)
    if request.map is not None:
        check_map_rights(request.map, who, settings.maps, bus.grants)
    config, folder = checked_start(request, settings)
    missing = bus.missing_services()
    if missing:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"services not running: {', '.join(missing)}")
    with _admitting:  # two requests at once must not both take the last share
        if table.active_for_robot(request.robot_id):
            raise HTTPException(status.HTTP_409_CONFLICT, f"robot {request.robot_id} already runs a session")
        admit(request, table, settings.max_robots)
        try:
            tracker = bus.trackers.place(request)
        except PlacementRefused as exc:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, str(exc)) from None
        session = Session(id=uuid.uuid4().hex[:12], request=request, folder=folder, started_by=identity(who.robot),
                          tracker=tracker, config=config)
        table.add(session)
    bus.send_control(session, "start", config)
    bus.audit.record("session.start", session.started_by, robot=request.robot_id, session=session.id,
                     map=request.map.name if request.map else None,
                     detail=request.source + (
                         f", {request.map.mode.value} map {request.map.name}" if request.map else ""))
    return session_info(session, settings.recordings)


@router.get("/sessions", response_model=list[SessionInfo], responses=errors(401))
def list_sessions(settings: Settings, table: Table, who: Who) -> list[SessionInfo]:
    """Every session the gateway knows: the active ones and the latest ended ones (a robot's token: its own)."""
    return [session_info(s, settings.recordings) for s in list(table.sessions.values())
            if who.robot in (None, s.request.robot_id)]


@router.get("/sessions/{session_id}", response_model=SessionInfo, responses=errors(401, 403, 404))
def get_session(session_id: str, settings: Settings, table: Table, who: Who) -> SessionInfo:
    """One session's state, progress, latest pose and ATE."""
    return session_info(lookup(table, session_id, who), settings.recordings)


@router.delete("/sessions/{session_id}", response_model=SessionInfo, responses=errors(401, 403, 404))
def stop_session(session_id: str, settings: Settings, bus: Bus, table: Table, who: Who) -> SessionInfo:
    """Stop a session (its robot is free at once); an ended session is returned unchanged."""
    session = lookup(table, session_id, who)
    if session.state in ACTIVE:
        session.state = "stopped"
        bus.send_control(session, "stop")
        bus.audit.record("session.stop", identity(who.robot), robot=session.request.robot_id, session=session.id)
    return session_info(session, settings.recordings)


@router.get("/sessions/{session_id}/trajectory", response_class=PlainTextResponse,
            responses=errors(401, 403, 404, 422))
async def trajectory(session_id: str, bus: Bus, table: Table, who: Who, online: bool = False) -> PlainTextResponse:
    """The session's trajectory in TUM format (camera-to-world). Once the session has ended: the refined
    trajectory the tracker sends then (final bundle adjustment, re-anchoring, smoothing), waited for a few
    seconds if it is not in yet; while it runs, or with ``online=true``: the poses as published. The header
    ``X-Twohr-Trajectory`` says which (``refined`` or ``online``)."""
    session = lookup(table, session_id, who)
    while not online and session.refined is None and session.refined_due is not None and (
            time.time() < session.refined_due) and bus.trackers.alive():
        await asyncio.sleep(0.1)
    refined = None if online else session.refined
    trajectory = session.trajectory() if refined is None else refined
    return PlainTextResponse(tum_text(trajectory),
                             headers={"X-Twohr-Trajectory": "online" if refined is None else "refined"})


@router.get("/sessions/{session_id}/recording",
            responses={200: {"content": {"application/octet-stream": {}},
                             "description": "the MCAP file; header X-Twohr-Recording: partial when the recorder "
                             "died and its readable prefix was re-indexed"}, **errors(401, 403, 404, 409)})
async def recording(session_id: str, settings: Settings, table: Table, who: Who) -> FileResponse:
    """The session's MCAP file, once the session has ended."""
    session = lookup(table, session_id, who)
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
