"""The gateway's side of the bus: it follows poses, statuses and service liveliness into the session table,
sends control messages, and ends sessions: finished (with their ATE), or failed when a service they need dies,
rejects their config, or the pipeline stalls. No HTTP here; the routers in ``routes/`` call it. The maps and the
sessions' map snapshots on the bus are the map room's (``twohr_services.mapserver``)."""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from twohr import keys
from twohr.bus import open_session
from twohr.config import PipelineConfig
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError
from twohr.evaluation import evaluate
from twohr.keys import PIPELINE_SERVICES
from twohr.mapmodes import MapMode
from twohr.messages import (
    ControlMsg,
    MergeMsg,
    MessageError,
    PathMsg,
    PoseMsg,
    StatusMsg,
    decode,
    encode,
    path_trajectory,
)
from twohr.service import declare_publisher

from .audit import STACK, AuditLog
from .live import BusLiveView, live_access
from .ownership import Grants
from .sessions import Session, SessionTable
from .tokens import Tokens
from .trackers import TrackerKind, Trackers, TrackerState

log = logging.getLogger("twohr.gateway")

class GatewayBus:
    """The gateway's Zenoh session and what it does with it (``settings`` is a ``GatewaySettings``; ``audit``: the
    audit trail, none by default; ``grants``: the operator's map grants, none by default; ``tokens``: the token check
    the live view shares with the HTTP API, made from the settings by default)."""

    def __init__(self, settings, table: SessionTable, audit: AuditLog | None = None,
                 grants: Grants | None = None, tokens: Tokens | None = None) -> None:
        self.settings = settings
        self.tokens = tokens
        self.table = table
        self.audit = audit or AuditLog(None)
        self.grants = grants or Grants(None)
        self.alive: dict[str, set[str]] = {}  # service -> its replicas whose liveliness token is up (not the tracker)
        self.trackers = Trackers(table)  # the trackers: which are alive, where sessions go, where they move
        self._gone: dict[str, float] = {}  # pipeline service -> when its token went, while it has not come back
        self._linked_since: float | None = 0.0  # when this gateway's own link to a router last came up
        self.session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscribers: list = []
        self._live: BusLiveView | None = None
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None

    def start(self) -> None:
        """Open the session, follow poses, statuses and liveliness, and start the session monitor."""
        self.session = open_session(self.settings.bus)
        self._subscribers = [
            self.session.declare_subscriber(keys.all_robots("pose"), self._decoded(PoseMsg, self.table.on_pose)),
            self.session.declare_subscriber(keys.all_robots("status"), self._decoded(StatusMsg, self._on_status)),
            self.session.declare_subscriber(keys.all_robots("path"), self._on_path),
            self.session.declare_subscriber(keys.merged_key(), self._decoded(MergeMsg, self.table.on_merge)),
            self.session.liveliness().declare_subscriber(keys.alive_key("*"), self._on_liveliness,
                                                         history=True)]
        if self.settings.foxglove_port:
            tls, authorize = live_access(self.settings, self.tokens)
            self._live = BusLiveView(self.session, self.settings.foxglove_host, self.settings.foxglove_port,
                                     tls=tls, authorize=authorize)
        self._monitor = threading.Thread(target=self._watch, name="session-monitor", daemon=True)
        self._monitor.start()

    def close(self) -> None:
        """Stop the monitor and the live view, and close the session."""
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(timeout=2)
        if self._live is not None:
            self._live.close()
        for sub in self._subscribers:
            sub.undeclare()
        if self.session is not None:
            self.session.close()

    def missing_services(self) -> list[str]:
        """The pipeline services whose liveliness token is not up."""
        return [name for name in PIPELINE_SERVICES if not (
            self.trackers.alive(TrackerKind.STACK) if name == "tracker" else self.alive.get(name))]

    def send_control(self, session: Session, command: str, config: PipelineConfig | None = None) -> None:
        """Publish a start, stop or move of ``session`` on ``twohr/<robot>/control`` (with ``config``, or the
        session's). After a stop, the tracker sends the refined trajectory of a session that has poses: it is waited
        for up to ``refine_timeout``."""
        req = session.request
        if command == "stop":
            if session.poses:
                session.refined_due = time.time() + self.settings.refine_timeout
        control = ControlMsg(session_id=session.id, robot_id=req.robot_id, frame_index=-1, stamp=time.time(),
                             command=command, sequence=str(session.folder or ""), rate=req.rate,
                             max_frames=req.max_frames, record=req.record, record_descriptors=req.record_descriptors,
                             record_frames=req.record_frames, start=req.start,
                             map_name=req.map.name if req.map else "",
                             map_mode=req.map.mode if req.map else MapMode.NONE, started_by=session.started_by,
                             config=config or session.config or PipelineConfig(), tracker=session.tracker)
        key = keys.key(req.robot_id, keys.CONTROL)
        if key not in self._publishers:
            self._publishers[key] = declare_publisher(self.session, key)
        self._publishers[key].put(encode(control))

    def _decoded(self, schema, handle):
        """A Zenoh callback that decodes ``schema`` and hands it to ``handle``; a malformed payload, or one whose
        robot is not its key's, is logged and dropped."""
        def callback(sample) -> None:
            try:
                message, _ = decode(sample.payload.to_bytes(), schema)
                robot, _ = keys.parse(sample.key_expr)
                # a map's key (twohr/maps/<name>/merged) speaks of any robot of the map: only the map server's
                if robot != message.robot_id and robot not in keys.RESERVED_ROBOT_IDS:
                    raise MessageError(f"a message for robot {message.robot_id!r} on {sample.key_expr}")
            except (MessageError, ValueError) as exc:
                log.warning("dropped %s on %s: %s", schema.__name__, sample.key_expr, exc)
                return
            handle(message)
        return callback

    def _on_path(self, sample) -> None:
        """A path from the tracker: a live correction is counted; the final, refined trajectory is kept and
        scored."""
        try:
            message, arrays = decode(sample.payload.to_bytes(), PathMsg)
            robot, _ = keys.parse(sample.key_expr)
            if robot != message.robot_id:
                raise MessageError(f"a message for robot {message.robot_id!r} on {sample.key_expr}")
            trajectory = path_trajectory(arrays)
        except (MessageError, ValueError) as exc:
            log.warning("dropped a path on %s: %s", sample.key_expr, exc)
            return
        session = self.table.on_path(message, trajectory)
        if session is not None:
            self._score(session)

    def _move_sessions(self, replica: str) -> None:
        """The sessions of a tracker that died go to the least loaded of the others, each told to go on in its
        map's latest snapshot (``move``); with no other tracker alive, they fail. A robot's own tracker's wait for it
        (:meth:`Trackers.rehome`)."""
        rehomed = self.trackers.rehome(replica)
        for session in rehomed.away:
            log.warning("session %s: the robot's own tracker %s is out of reach", session.id, replica)
        for session in rehomed.failed:
            session.state, session.detail = "failed", f"its tracker {replica} stopped during the session"
            self._fail(session)
        for session in rehomed.moved:
            target = session.tracker
            log.warning("session %s: its tracker %s stopped; it moves to tracker %s", session.id, replica, target)
            self.audit.record("session.move", STACK, robot=session.request.robot_id, session=session.id,
                              detail=f"tracker {replica} stopped; now on {target}")
            self.send_control(session, "move")

    def _score(self, session: Session) -> None:
        """The ATE of the online poses and, once it is in, of the refined trajectory (when ground truth exists)."""
        try:
            if session.folder is None:
                raise TwohrError("a camera session has no ground truth")
            seq = RGBDSequence(session.folder)
            if not seq.has_ground_truth() or len(session.poses) < 3:
                return
            gt = seq.ground_truth(seq.default_gt_extrinsic())
            session.ate_rmse_online = evaluate(gt, session.trajectory())[0].ate.rmse
            served = session.refined if session.refined is not None and len(session.refined) >= 3 else None
            session.ate_rmse = session.ate_rmse_online if served is None else evaluate(gt, served)[0].ate.rmse
        except (TwohrError, ValueError) as exc:
            session.detail = f"no ATE: {exc}"

    def _fail(self, session: Session) -> None:
        log.warning("session %s failed: %s", session.id, session.detail)
        self.audit.record("session.fail", STACK, robot=session.request.robot_id, session=session.id,
                          detail=session.detail)
        self.send_control(session, "stop")

    def _on_status(self, status: StatusMsg) -> None:
        failed = self.table.on_status(status)
        if failed is not None:
            self._fail(failed)

    def _on_liveliness(self, sample) -> None:
        """A replica's token came or went; a service is gone when its last replica's token went."""
        try:
            name, replica = keys.parse_replica_key(sample.key_expr)
        except ValueError:
            return
        if name == "tracker":
            self._on_tracker(replica, up=sample.kind == zenoh.SampleKind.PUT)
            return
        replicas = self.alive.setdefault(name, set())
        if sample.kind == zenoh.SampleKind.PUT:
            replicas.add(replica)
            return
        replicas.discard(replica)
        # an optional service (the ros2 bridge) is not part of a session's pipeline
        if not replicas and name in PIPELINE_SERVICES:
            self._gone.setdefault(name, time.monotonic())

    def _on_tracker(self, replica: str, up: bool) -> None:
        """A tracker's token came (a robot's own tracker back in reach: its sessions go on) or went: the tracker
        service is gone with the stack's last tracker (a robot's own is not the stack's); else the sessions assigned
        to this one have lost their tracker."""
        if up:
            for session in self.trackers.came(replica):
                log.info("session %s: the robot's own tracker %s is in reach again", session.id, replica)
            return
        self.trackers.went(replica)
        if not self.trackers.alive(TrackerKind.STACK):
            self._gone.setdefault("tracker", time.monotonic())
        else:  # one tracker of several
            self._gone.setdefault(f"tracker {replica}", time.monotonic())

    def _fail_for_gone_services(self) -> None:
        """Fail the active sessions once a pipeline service's token has stayed away for ``liveliness_grace`` while
        this gateway stayed linked to its router; where one tracker of several went, move its sessions
        (:meth:`_move_sessions`). A token that went because this gateway's own link went (the
        router restarting, as a fleet's revocation makes it) is not a dead service: the tokens come back with the
        link, and the sessions go on."""
        now = time.monotonic()
        if not list(self.session.info.routers_zid()):
            self._linked_since = None
            self._gone.clear()
            return
        if self._linked_since is None:
            self._linked_since = now
        for name, since in list(self._gone.items()):
            _, _, replica = name.partition(" ")  # "tracker <replica>": one tracker of several
            back = (self.trackers.state(replica) is TrackerState.ALIVE if replica
                    else name not in self.missing_services())
            if back or since < self._linked_since:
                del self._gone[name]
            elif now - since >= self.settings.liveliness_grace:
                del self._gone[name]
                if replica:
                    self._move_sessions(replica)
                    continue
                # a session on a robot's own tracker needs none of the stack's trackers
                def needs_it(session: Session, service: str = name) -> bool:
                    return service != "tracker" or self.trackers.needs_stack(session)

                for session in self.table.fail_active(f"the {name} service stopped during the session", needs_it):
                    self._fail(session)

    def _finish(self, session: Session) -> None:
        self._score(session)
        self.send_control(session, "stop")
        session.state = "finished"
        self.audit.record("session.finish", STACK, robot=session.request.robot_id, session=session.id,
                          detail=f"{len(session.poses)} poses")

    def _watch(self) -> None:
        settings = self.settings
        while not self._stop.wait(0.25):
            self._fail_for_gone_services()
            for session in self.table.finished_sessions(settings.idle_timeout):
                self._finish(session)
            for session in self.table.stalled_sessions(settings.start_timeout, settings.stall_timeout):
                self._fail(session)
            self.table.forget_ended(settings.keep_ended)
