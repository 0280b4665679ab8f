"""The gateway's side of the bus: it follows poses, statuses and service liveliness into the session table,
sends control messages, and ends sessions: finished (with their ATE), or failed when a service they need dies,
rejects their config, or the pipeline stalls. It also keeps the map store on the bus (``--maps``). No HTTP here; the
routers in ``routes/`` call it."""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import zenoh

from twohr import keys
from twohr.bus import open_session
from twohr.config import PipelineConfig
from twohr.dataset import RGBDSequence
from twohr.errors import TwohrError
from twohr.evaluation import evaluate
from twohr.keys import PIPELINE_SERVICES
from twohr.mapfile import OPERATOR, MapAccessError, MapFileError, MapMissingError, MapStore
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

from .admission import least_loaded_tracker, stack_trackers
from .audit import STACK, AuditLog
from .live import BusLiveView, live_access
from .ownership import Grants
from .sessions import Session, SessionTable
from .tokens import Tokens

log = logging.getLogger("twohr.gateway")

#: threads that read and save map files for the map store's queries: a save waiting on the store (another save, a
#: slow disk) takes one, and reads and other saves go on in the others
MAP_STORE_WORKERS = 4


#: a session's detail while its robot's own tracker (``twohr camera --edge``) is out of reach: the robot tracks on
OWN_TRACKER_AWAY = "the robot's own tracker is out of reach (its link or its process): its poses come back with it"


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
        self.alive: dict[str, set[str]] = {}  # service -> its replicas whose liveliness token is up
        self._gone: dict[str, float] = {}  # pipeline service -> when its token went, while it has not come back
        self._linked_since: float | None = 0.0  # when this gateway's own link to a router last came up
        self.session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscribers: list = []
        self._live: BusLiveView | None = None
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None
        self._map_store: ThreadPoolExecutor | None = None

    def start(self) -> None:
        """Open the session, follow poses, statuses and liveliness, and start the session monitor."""
        self.session = open_session(self.settings.bus)
        self._subscribers = [
            self.session.declare_subscriber(keys.all_robots("pose"), self._decoded(PoseMsg, self.table.on_pose)),
            self.session.declare_subscriber(keys.all_robots("status"), self._decoded(StatusMsg, self._on_status)),
            self.session.declare_subscriber(keys.all_robots("path"), self._on_path),
            # each session's latest map snapshot, kept here for the tracker it moves to when its own dies
            self.session.declare_subscriber(keys.snapshot_key(), self._on_snapshot),
            self.session.declare_subscriber(keys.merged_key(), self._decoded(MergeMsg, self.table.on_merge)),
            self.session.declare_queryable(keys.snapshot_key(), self._serve_snapshot),
            self.session.liveliness().declare_subscriber(keys.alive_key("*"), self._on_liveliness,
                                                         history=True)]
        if self.settings.maps is not None:  # the map store: read by trackers and clients, written by trackers
            self._map_store = ThreadPoolExecutor(MAP_STORE_WORKERS, thread_name_prefix="map-store")
            self._subscribers += [
                self.session.declare_queryable(f"{keys.MAPS_PREFIX}/*", self._handed_on(self._read_map)),
                self.session.declare_queryable(f"{keys.MAPS_PREFIX}/*/save", self._handed_on(self._save_map))]
        if self.settings.foxglove_port:
            tls, authorize = live_access(self.settings, self.tokens)
            self._live = BusLiveView(self.session, self.settings.foxglove_host, self.settings.foxglove_port,
                                     tls=tls, authorize=authorize)
        self._monitor = threading.Thread(target=self._watch, name="session-monitor", daemon=True)
        self._monitor.start()

    def close(self) -> None:
        """Stop the monitor and the live view, answer the map queries already taken, and close the session."""
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(timeout=2)
        if self._live is not None:
            self._live.close()
        for sub in self._subscribers:
            sub.undeclare()
        if self._map_store is not None:  # no new queries come: the ones taken are answered before the session goes
            self._map_store.shutdown(wait=True)
        if self.session is not None:
            self.session.close()

    def _handed_on(self, answer):
        """A queryable callback that hands each query to the map store's workers, which run ``answer(query)``: the
        file I/O stays off Zenoh's callback thread, which takes the next query at once. The query object travels
        with the work (it is answered there) and is dropped once answered, which ends it for the caller."""
        def callback(query: zenoh.Query) -> None:
            try:
                self._map_store.submit(self._answer, answer, query)
            except RuntimeError:  # shut down: the gateway is closing
                query.reply_err(b"the gateway is closing")
                query.drop()
        return callback

    @staticmethod
    def _answer(answer, query: zenoh.Query) -> None:
        """Run ``answer(query)`` on a worker; whatever it raises is logged (the query is ended either way)."""
        try:
            answer(query)
        except Exception:
            log.exception("map store query %s failed", query.key_expr)
        finally:
            query.drop()

    def _read_map(self, query: zenoh.Query) -> None:
        """``twohr/maps/<name>``: the latest version's bytes of a map in the store."""
        try:
            name = keys.parse_map_key(query.key_expr)
            query.reply(query.key_expr, MapStore(self.settings.maps).latest_file(name).read_bytes())
        except (FileNotFoundError, MapMissingError):
            query.reply_err(f"no map named {name!r} in the map store".encode())
        except (ValueError, MapFileError, OSError) as exc:  # a key naming no single map, a bad file
            query.reply_err(str(exc).encode())

    def _save_map(self, query: zenoh.Query) -> None:
        """``twohr/maps/<name>/save`` with a map file's bytes: checked, kept as the map's next version. The tracker
        attaches the id of the session that built it: the session's robot is its builder (the owner of a new map, a
        contributor to another's), and replacing an existing map needs whoever started the session to own it or
        hold the operator's grant. Only
        the tracker may save (the bus's access control); a save naming no session is the stack's, the operator's."""
        name, session = str(query.key_expr), None
        try:
            name = keys.parse_map_key(query.key_expr, save=True)
            if query.payload is None:
                raise MapFileError("a save carries the map file's bytes")
            session = self._saving_session(query, name)
            builder, starter = (OPERATOR, OPERATOR) if session is None else (session.request.robot_id,
                                                                            session.started_by)
            entry = MapStore(self.settings.maps, self.settings.map_versions).save(
                query.payload.to_bytes(), name, builder=builder,
                may_replace=lambda owners: self.grants.may_change(starter, name, owners))
            log.info("map %s version %d saved (%d keyframes, %d bytes)", name, entry.version, entry.keyframes,
                     entry.size_bytes)
            by_session = {} if session is None else {"robot": builder, "session": session.id}
            self.audit.record("map.save", STACK if session is None else starter, map=name, version=entry.version,
                              detail=f"owners {', '.join(entry.owners)}" + (
                                  f"; contributors {', '.join(entry.contributors)}" if entry.contributors else ""),
                              **by_session)
            query.reply(query.key_expr, entry.model_dump_json())
        except (ValueError, MapFileError, OSError) as exc:  # a key naming no single map, a bad file, not theirs
            log.warning("map %s not saved: %s", name, exc)
            if isinstance(exc, MapAccessError) and session is not None:
                self.audit.record("map.save", session.started_by, robot=session.request.robot_id, map=name,
                                  session=session.id, detail=f"refused: {exc}")
            query.reply_err(str(exc).encode())

    def _saving_session(self, query: zenoh.Query, name: str) -> Session | None:
        """The session a save's attachment names (None: it names none); :class:`MapAccessError` when that is no
        session of this gateway that builds or extends map ``name``."""
        if query.attachment is None:
            return None
        session_id = query.attachment.to_bytes().decode(errors="replace")[:64]
        session = self.table.get(session_id)
        wanted = None if session is None else session.request.map
        # a shared map is saved by the map server, and a robot of it that never merged as map <name>.<robot>
        names = (wanted.name, f"{wanted.name}.{session.request.robot_id}") if wanted and wanted.mode.shared else (
            () if wanted is None else (wanted.name,))
        if wanted is None or name not in names or not wanted.mode.saves:
            raise MapAccessError(f"session {session_id!r} is no session of this gateway that builds, extends or "
                                 f"shares map {name}")
        return session

    def missing_services(self) -> list[str]:
        """The pipeline services whose liveliness token is not up."""
        return [name for name in PIPELINE_SERVICES if not (
            stack_trackers(self.alive.get(name, set())) if name == "tracker" else self.alive.get(name))]

    def send_control(self, session: Session, command: str, config: PipelineConfig | None = None) -> None:
        """Publish a start, stop or move of ``session`` on ``twohr/<robot>/control`` (with ``config``, or the
        session's). After a stop, the tracker sends the refined trajectory of a session that has poses: it is waited
        for up to ``refine_timeout``."""
        req = session.request
        if command == "stop":
            session.snapshot = None
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

    def _snapshot_session(self, key_expr, attachment) -> Session | None:
        """The active session a snapshot key and its attachment (the session's id) name, or None."""
        try:
            robot = str(key_expr).split("/")[1]
            session_id = attachment.to_bytes().decode(errors="replace") if attachment is not None else ""
        except IndexError:
            return None
        session = self.table.active_for_robot(robot)
        return session if session is not None and session.id == session_id else None

    def _on_snapshot(self, sample) -> None:
        """A tracker's latest copy of a session's map: kept while the session is active (the previous one goes)."""
        session = self._snapshot_session(sample.key_expr, sample.attachment)
        if session is not None:
            session.snapshot = sample.payload.to_bytes()

    def _serve_snapshot(self, query: zenoh.Query) -> None:
        """``twohr/<robot>/map/snapshot``, the session's id attached: the latest snapshot of its map, for the
        tracker the session moved to."""
        session = self._snapshot_session(query.key_expr, query.attachment)
        if session is None or session.snapshot is None:
            query.reply_err(b"no snapshot of this session's map")
        else:
            query.reply(query.key_expr, session.snapshot)

    def _move_sessions(self, replica: str) -> None:
        """The sessions of a tracker that died go to the least loaded of the others, each told to go on in its
        map's latest snapshot (``move``); with no other tracker alive, they fail."""
        others = stack_trackers(self.alive.get("tracker", set()) - {replica})
        for session in self.table.active():
            if session.tracker != replica:
                continue
            if keys.edge_robot(replica) is not None:  # its frames are the robot's: none reach another tracker
                session.detail = OWN_TRACKER_AWAY
                log.warning("session %s: the robot's own tracker %s is out of reach", session.id, replica)
                continue
            target = least_loaded_tracker(others, self.table, always=True)
            if not target:
                session.state, session.detail = "failed", f"its tracker {replica} stopped during the session"
                self._fail(session)
                continue
            session.tracker, session.moves = target, session.moves + 1
            log.warning("session %s: its tracker %s stopped; it moves to tracker %s", session.id, replica, target)
            self.audit.record("session.move", STACK, robot=session.request.robot_id, session=session.id,
                              detail=f"tracker {replica} stopped; now on {target}" + (
                                  "" if session.snapshot else ", with no map snapshot"))
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
        replicas = self.alive.setdefault(name, set())
        if sample.kind == zenoh.SampleKind.PUT:
            replicas.add(replica)
            for session in self.table.active():  # a robot's own tracker in reach again
                if session.tracker == replica and session.detail == OWN_TRACKER_AWAY:
                    session.detail = ""
            return
        replicas.discard(replica)
        # an optional service (the ros2 bridge) is not part of a session's pipeline; a robot's own tracker is not
        # the stack's
        if not (stack_trackers(replicas) if name == "tracker" else replicas) and name in PIPELINE_SERVICES:
            self._gone.setdefault(name, time.monotonic())
        elif name == "tracker":  # the sessions placed on this one have lost their tracker
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
            service, _, replica = name.partition(" ")  # "tracker <replica>": one tracker of several
            back = replica in self.alive.get(service, set()) if replica else name not in self.missing_services()
            if back or since < self._linked_since:
                del self._gone[name]
            elif now - since >= self.settings.liveliness_grace:
                del self._gone[name]
                if replica:
                    self._move_sessions(replica)
                    continue
                # a session on a robot's own tracker needs none of the stack's trackers
                def needs_it(session: Session, service: str = name) -> bool:
                    return service != "tracker" or keys.edge_robot(session.tracker) is None

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
