"""The map room: the map store on the bus, each live session's latest map snapshot, and one map built by many robots
at once for the sessions that share a map.

The store (``--maps DIR``, :class:`~.room.MapRoom`) answers ``twohr/maps/<name>`` with a stored map's bytes and keeps
the map a query on ``twohr/maps/<name>/save`` carries as its next version, checked against the session that built it
(the protocol: :mod:`twohr.mapclient`); the file I/O runs on a few worker threads, off Zenoh's callback thread and
off the shared maps' thread. The trackers' snapshots (``twohr/<robot>/map/snapshot``) are kept while their session
is active and handed to the tracker a session moves to when its own died.

Sessions started with ``"map": {"name": "lab", "mode": "share"}`` send their robot's keyframes here
(``twohr/<robot>/keyframes``, from the robot's tracker, on the stack or on the robot). The map server keeps each
shared map while robots build it (:class:`~.core.SharedMap`) and, when a robot's keyframes are found in the map,
publishes the merge on ``twohr/maps/<name>/merged``: the robot's tracker puts its poses in the map's frame from then
on, and sends its earlier path again, moved. When the map's last session has ended (and its tracker's last
keyframes came), the map is saved in the map store as its next version; a robot that never merged is saved as map
``<name>.<robot>``, and its session's status says so. The stored map a shared map starts from is read from the store
here once; the trackers of its sessions fetch it over the bus.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import zenoh
from pydantic import ValidationError

from twohr import keys
from twohr.bus import BusConfig, bus_from_args
from twohr.config import PipelineConfig
from twohr.errors import TwohrError, validation_problems
from twohr.features import mutual_nn
from twohr.geometry import rot_to_quat
from twohr.mapclient import NO_SNAPSHOT
from twohr.mapfile import MapFileError, arrays_file, encode_map
from twohr.messages import ControlMsg, KeyframesMsg, MergeMsg, MessageError, decode, encode
from twohr.service import Service, UnknownSession, one_line_errors, service_parser

from .core import STORED, BatchRefused, KeyframeBatch, MergeEvent, SharedMap, check_batch, export
from .room import MapRoom, MapRoomSettings

#: how long after a session's stop its tracker's last keyframes are waited for (the final bundle adjustment)
FINAL_WAIT_S = 30.0
#: threads that read and save map files for the store's queries: a save waiting on the store (another save, a slow
#: disk) takes one, and reads and other saves go on in the others
STORE_WORKERS = 4


@dataclass
class SharedSession:
    """A session that shares a map: its start, and what crossed the wire for it."""

    control: ControlMsg
    bytes_in: int = 0
    bytes_out: int = 0
    keyframes: int = 0
    corrections: int = 0  # its transform refined after its merge
    ended_at: float | None = None  # when its stop came (monotonic)
    final: bool = False  # its tracker's last keyframes came


@dataclass
class OpenMap:
    """A shared map while robots build it: the core's map and its sessions, by id."""

    shared_map: SharedMap
    config: PipelineConfig
    sessions: dict[str, SharedSession] = field(default_factory=dict)
    merged_into: list[str] = field(default_factory=list)  # submap keys, in the order they entered the map's frame
    work_s: float = 0.0  # the map server's thread's CPU on this map (its keyframes taken in, searched, merged)


class MapServerService(Service):
    """The map room (see the module docstring): the store's queries and the snapshots on the bus, every shared map
    while robots build it on this service's thread."""

    name = "mapserver"
    follows_sessions = True

    def __init__(self, bus: BusConfig | None = None, settings: MapRoomSettings | None = None) -> None:
        super().__init__(bus, queue_size=256, policy="backpressure")
        self.room = MapRoom(settings or MapRoomSettings())
        self.maps: dict[str, OpenMap] = {}
        self.sessions: dict[str, str] = {}  # session -> its map's name
        self._store_workers = ThreadPoolExecutor(STORE_WORKERS, thread_name_prefix="map-store")
        self._declared: list = []

    def subscriptions(self) -> list[str]:
        return [keys.all_robots("keyframes")]

    def on_start(self) -> None:
        """The snapshots followed and served; with a store, the store's queries answered."""
        self._declared = [self.session.declare_subscriber(keys.snapshot_key(), self._on_snapshot),
                          self.session.declare_queryable(keys.snapshot_key(), self._serve_snapshot)]
        if self.room.store is not None:
            self._declared += [
                self.session.declare_queryable(keys.map_key("*"), self._handed_on(self._read_map)),
                self.session.declare_queryable(keys.map_key("*", save=True), self._handed_on(self._save_map))]

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set; the store's queries already taken are answered before the bus session
        closes."""
        super().run(_AnsweredFirst(stop or self.stopping, self._store_workers))

    def health(self) -> dict:
        """Its counters, the reads of each stored map (``reads``: map name -> how often its bytes were read) and
        the snapshots kept now."""
        return super().health() | {"reads": self.room.read_counts(), "snapshots": self.room.sessions.snapshots()}

    def on_session_start(self, control: ControlMsg) -> None:
        self.room.sessions.started(control)
        if not control.map_mode.shared:
            return
        opened = self.maps.get(control.map_name)
        if opened is None:
            stored = None if self.room.store is None else self.room.stored(control.map_name,
                                                                            control.config.detector)
            shared_map = SharedMap(control.map_name, mutual_nn, control.config.loop_closing, control.config.tracker,
                                   stored=stored)
            opened = self.maps[control.map_name] = OpenMap(shared_map, control.config)
            if stored is not None:
                opened.merged_into.append(STORED)
        opened.sessions[control.session_id] = SharedSession(control)
        self.sessions[control.session_id] = control.map_name
        event = opened.shared_map.join(control.robot_id, control.session_id)
        if event is not None:
            self._merged(opened, event)
        else:
            self.report(control, "sharing", f"map {control.map_name}: robot {control.robot_id} starts in a submap of "
                        f"its own (frame {control.map_name}/{control.robot_id}) until its places are found in the map")

    def on_session_stop(self, session_id: str) -> None:
        self.room.sessions.stopped(session_id)
        name = self.sessions.get(session_id)
        if name is not None:
            self.maps[name].sessions[session_id].ended_at = time.monotonic()

    def handle(self, key: str, payload: bytes) -> None:
        message, arrays = decode(payload, KeyframesMsg)
        name = self.sessions.get(message.session_id)
        if name is None or name != message.map_name:
            raise UnknownSession(message.session_id)
        opened = self.maps[name]
        began = time.thread_time()
        session = opened.sessions[message.session_id]
        batch = KeyframeBatch(first=message.first, **{part: arrays[part] for part in KeyframesMsg.required_arrays})
        try:
            check_batch(batch, *session.control.config.detector.descriptor_layout)
        except BatchRefused as exc:
            self.report(session.control, "refused", f"map {name}: a keyframe batch refused: {exc}")
            raise MessageError(f"keyframes of session {message.session_id}: {exc}") from None
        session.bytes_in += len(payload)
        session.final = session.final or message.final
        submap = opened.shared_map.submaps.get(message.robot_id)
        if submap is None or submap.session != message.session_id:
            return  # an earlier session of the robot, still finishing: its keyframes are in the map already
        event = opened.shared_map.add(message.robot_id, batch, message.camera)
        session.keyframes = len(opened.shared_map.submaps[message.robot_id])
        if event is not None:
            self._merged(opened, event)
        opened.work_s += time.thread_time() - began

    def process_one(self, timeout: float = 0.2) -> bool:
        handled = super().process_one(timeout)
        now = time.monotonic()
        for name, opened in list(self.maps.items()):
            if all(s.ended_at is not None and (s.final or now - s.ended_at > FINAL_WAIT_S)
                   for s in opened.sessions.values()):
                try:
                    self._close(name, opened)
                except Exception:  # a map that cannot be saved is one map's error, never the room's exit
                    self.counters.add("errors")
                    self.log.exception("map %s: closing it failed", name)
        return handled

    def _merged(self, opened: OpenMap, event: MergeEvent) -> None:
        """A robot placed in the map's frame: said on ``twohr/maps/<name>/merged`` and on its session's status."""
        name = opened.shared_map.name
        if event.robot not in opened.merged_into:
            opened.merged_into.append(event.robot)
        session = opened.sessions[event.session]
        merge = MergeMsg(session_id=event.session, robot_id=event.robot, frame_index=-1, stamp=event.stamp,
                         map_name=name, kind=event.kind, position=event.T[:3, 3].tolist(),
                         orientation=rot_to_quat(event.T[:3, :3]).tolist(),
                         into=sorted({m.into for m in event.matches}), inliers=[m.inliers for m in event.matches],
                         keyframes=event.keyframes, at=time.time(), ms=round(event.ms, 1))
        payload = encode(merge)
        session.bytes_out += len(payload)
        session.corrections += event.kind == "refined"
        self.publish(keys.merged_key(name), payload)
        if event.kind == "merged":
            self.report(session.control, "merged", f"map {name}: robot {event.robot} merged at its keyframe "
                        f"{event.keyframes} ({len(event.matches)} agreeing matches, inliers "
                        f"{', '.join(map(str, merge.inliers))}; search {event.ms:.0f} ms); its poses are in frame "
                        f"{name} now", keyframes=event.keyframes)

    def _close(self, name: str, opened: OpenMap) -> None:
        """The map's last session ended: the map saved as its next version, robots that never merged as maps of
        their own; each session told its bytes."""
        del self.maps[name]
        for session_id in opened.sessions:
            self.sessions.pop(session_id, None)
        shared_map = opened.shared_map
        merged = [key for key in opened.merged_into if key in shared_map.submaps]
        first = next(s for s in opened.sessions.values())  # the session that opened the map saves it
        self._save(name, export(shared_map, merged), opened, first.control, "robots " + ", ".join(
            sorted({shared_map.submaps[k].robot for k in merged if k != STORED})))
        for key, submap in shared_map.submaps.items():
            if submap.T is None and len(submap):
                own = f"{name}.{submap.robot}"
                control = opened.sessions[submap.session].control
                if self._save(own, export(shared_map, [key]), opened, control, f"robot {submap.robot}"):
                    self.report(control, "not merged", f"robot {submap.robot}'s places were never found in map "
                                f"{name}: its {len(submap)} keyframes are saved as map {own}")
        self.log.info("map %s closed: %.2f s of this thread's CPU on its %d keyframes", name, opened.work_s,
                      sum(len(s) for s in shared_map.submaps.values()))
        for session in opened.sessions.values():
            self.report(session.control, "shared", f"map {name}: {session.keyframes} keyframes in, "
                        f"{session.bytes_in} bytes in, {session.bytes_out} bytes out ({session.corrections} "
                        "refinements of its transform)", keyframes=session.keyframes, bytes_in=session.bytes_in,
                        bytes_out=session.bytes_out, corrections=session.corrections,
                        map_cpu_ms=round(opened.work_s * 1000))

    def _save(self, name: str, exported, opened: OpenMap, control: ControlMsg, built_by: str) -> bool:
        """One map file saved in the map store on behalf of ``control``'s session; False (and said) where not."""
        if not len(exported.arrays.keyframe_stamps):
            return False
        try:
            stored = arrays_file(exported.arrays, exported.cameras[0], opened.config, name,
                                 built_by=f"shared map {opened.shared_map.name}: {built_by}",
                                 parent=None if opened.shared_map.stored is None else opened.shared_map.stored.header,
                                 cameras=exported.cameras[1:], camera_robots=exported.robots)
            payload = encode_map(stored)
        except (MapFileError, ValueError) as exc:  # a pydantic ValidationError is a ValueError
            self.report(control, "error", f"map {name} not saved: {exc}")
            return False
        if self.room.store is None:
            self.report(control, "error", f"map {name} not saved: this map room keeps no map store (twohr up --maps "
                        "DIR)")
            return False
        try:
            self.room.save_for(payload, name, control)
        except (TwohrError, OSError) as exc:
            self.log.warning("map %s not saved: %s", name, exc)
            self.report(control, "error", f"map {name} not saved: {exc}")
            return False
        self.report(control, "map saved", f"map {name}: {stored.header.keyframes} keyframes, "
                    f"{stored.header.landmarks} landmarks", keyframes=stored.header.keyframes,
                    landmarks=stored.header.landmarks)
        return True

    # -- the store and the snapshots on the bus
    def _handed_on(self, answer):
        """A queryable callback that hands each query to the store's workers, which run ``answer(query)``: the file
        I/O stays off Zenoh's callback thread, which takes the next query at once. The query travels with the work
        and is dropped once answered, which ends it for the caller."""
        def callback(query: zenoh.Query) -> None:
            try:
                self._store_workers.submit(self._answer, answer, query)
            except RuntimeError:  # shut down: the map room is closing
                query.reply_err(b"the map room is closing")
                query.drop()
        return callback

    def _answer(self, answer, query: zenoh.Query) -> None:
        """Run ``answer(query)`` on a worker; whatever it raises is logged (the query is ended either way)."""
        try:
            answer(query)
        except Exception:
            self.counters.add("errors")
            self.log.exception("map store query %s failed", query.key_expr)
        finally:
            query.drop()

    def _read_map(self, query: zenoh.Query) -> None:
        """``twohr/maps/<name>``: the latest version's bytes of a stored map."""
        try:
            name = keys.parse_map_key(query.key_expr)
            query.reply(query.key_expr, self.room.read(name))
        except (ValueError, TwohrError, OSError) as exc:  # a key naming no single map, no such map, a bad file
            query.reply_err(str(exc).encode())

    def _save_map(self, query: zenoh.Query) -> None:
        """``twohr/maps/<name>/save`` with a map file's bytes, the id of the session that built it attached (none:
        the operator's): checked, kept as the map's next version (:meth:`.room.MapRoom.save`)."""
        name = str(query.key_expr)
        try:
            name = keys.parse_map_key(query.key_expr, save=True)
            if query.payload is None:
                raise MapFileError("a save carries the map file's bytes")
            session_id = None if query.attachment is None else query.attachment.to_bytes().decode(
                errors="replace")[:64]
            entry = self.room.save(query.payload.to_bytes(), name, session_id)
            self.log.info("map %s version %d saved (%d keyframes, %d bytes)", name, entry.version, entry.keyframes,
                          entry.size_bytes)
            query.reply(query.key_expr, entry.model_dump_json())
        except (ValueError, TwohrError, OSError) as exc:  # a key naming no single map, a bad file, not theirs
            self.log.warning("map %s not saved: %s", name, exc)
            query.reply_err(str(exc).encode())

    def _on_snapshot(self, sample: zenoh.Sample) -> None:
        """A tracker's latest copy of a session's map: kept while the session is active (the previous one goes)."""
        robot, session_id = _snapshot_of(sample.key_expr, sample.attachment)
        if not self.room.sessions.keep_snapshot(robot, session_id, sample.payload.to_bytes()):
            self.counters.add("ignored")  # no active session of that robot and id

    def _serve_snapshot(self, query: zenoh.Query) -> None:
        """``twohr/<robot>/map/snapshot``, the session's id attached: the latest snapshot of its map, for the
        tracker the session moved to."""
        snapshot = self.room.sessions.snapshot(*_snapshot_of(query.key_expr, query.attachment))
        if snapshot is None:
            query.reply_err(NO_SNAPSHOT.encode())
        else:
            query.reply(query.key_expr, snapshot)


def _snapshot_of(key_expr, attachment) -> tuple[str, str]:
    """(robot, session id) a snapshot's key and attachment name ('' where they name none)."""
    parts = str(key_expr).split("/")
    robot = parts[1] if len(parts) > 1 else ""
    return robot, "" if attachment is None else attachment.to_bytes().decode(errors="replace")[:64]


class _AnsweredFirst:
    """The stop event the service shell's loop watches: once ``stop`` is set, the store's queries already taken are
    answered first (the shell closes the bus session when its loop ends)."""

    def __init__(self, stop: threading.Event, workers: ThreadPoolExecutor) -> None:
        self.stop, self.workers = stop, workers

    def is_set(self) -> bool:
        if not self.stop.is_set():
            return False
        self.workers.shutdown(wait=True)
        return True


def build_parser():
    """The map room's command line: the options every service takes (``--router``) and one flag per field of
    :class:`~.room.MapRoomSettings`."""
    parser = service_parser("mapserver", __doc__)
    fields = MapRoomSettings.model_fields
    parser.add_argument("--maps", default=None, metavar="DIR", help=fields["maps"].description)
    parser.add_argument("--map-versions", type=int, default=None, metavar="N",
                        help=f"{fields['map_versions'].description} (default {fields['map_versions'].default})")
    parser.add_argument("--map-grants", default=None, metavar="FILE", help=fields["map_grants"].description)
    parser.add_argument("--audit-log", default=None, metavar="FILE", help=fields["audit_log"].description)
    return parser


def settings_from_args(args) -> MapRoomSettings:
    """The map room's settings from its parsed command line; :class:`TwohrError` (one line) for ones that cannot
    be."""
    given = {name: getattr(args, name) for name in MapRoomSettings.model_fields if getattr(args, name) is not None}
    try:
        return MapRoomSettings(**given)
    except ValidationError as exc:
        raise TwohrError(f"invalid settings: {validation_problems(exc)}") from None


@one_line_errors("mapserver")
def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    MapServerService(bus_from_args(args), settings_from_args(args)).run_forever()
