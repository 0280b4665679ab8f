"""The map server: one map built by many robots at once, for the sessions that share a map.

Sessions started with ``"map": {"name": "lab", "mode": "share"}`` send their robot's keyframes here
(``twohr/<robot>/keyframes``, from the robot's tracker, on the stack or on the robot). The map server keeps each
shared map while robots build it (:class:`~.core.SharedMap`) and, when a robot's keyframes are found in the map,
publishes the merge on ``twohr/maps/<name>/merged``: the robot's tracker puts its poses in the map's frame from then
on, and sends its earlier path again, moved. When the map's last session has ended (and its tracker's last
keyframes came), the map is saved in the map store as its next version; a robot that never merged is saved as map
``<name>.<robot>``, and its session's status says so.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from twohr import keys
from twohr.bus import BusConfig, bus_from_args
from twohr.config import PipelineConfig
from twohr.errors import TwohrError
from twohr.features import mutual_nn
from twohr.geometry import rot_to_quat
from twohr.mapfile import MapFile, MapFileError, arrays_file, encode_map, read_map
from twohr.messages import ControlMsg, KeyframesMsg, MergeMsg, decode, encode
from twohr.service import Service, UnknownSession, one_line_errors, service_parser

from .core import STORED, KeyframeBatch, MergeEvent, SharedMap, export

#: how long after a session's stop its tracker's last keyframes are waited for (the final bundle adjustment)
FINAL_WAIT_S = 30.0
#: a map store that does not answer in this time is not there
STORE_TIMEOUT_S = 10.0


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

    shared: SharedMap
    config: PipelineConfig
    sessions: dict[str, SharedSession] = field(default_factory=dict)
    merged_into: list[str] = field(default_factory=list)  # submap keys, in the order they entered the map's frame
    work_s: float = 0.0  # the map server's thread's CPU on this map (its keyframes taken in, searched, merged)


class MapServerService(Service):
    """Holds every shared map while robots build it (see the module docstring)."""

    name = "mapserver"
    follows_sessions = True

    def __init__(self, bus: BusConfig | None = None) -> None:
        super().__init__(bus, queue_size=256, policy="backpressure")
        self.maps: dict[str, OpenMap] = {}
        self.sessions: dict[str, str] = {}  # session -> its map's name

    def subscriptions(self) -> list[str]:
        return [keys.all_robots("keyframes")]

    def on_session_start(self, control: ControlMsg) -> None:
        if not control.map_mode.shared:
            return
        opened = self.maps.get(control.map_name)
        if opened is None:
            stored = self._fetch(control)
            shared = SharedMap(control.map_name, mutual_nn, control.config.loop_closing, control.config.tracker,
                               stored=stored)
            opened = self.maps[control.map_name] = OpenMap(shared, control.config)
            if stored is not None:
                opened.merged_into.append(STORED)
        opened.sessions[control.session_id] = SharedSession(control)
        self.sessions[control.session_id] = control.map_name
        event = opened.shared.join(control.robot_id, control.session_id)
        if event is not None:
            self._merged(opened, event)
        else:
            self.report(control, "sharing", f"map {control.map_name}: robot {control.robot_id} starts in a submap of "
                        f"its own (frame {control.map_name}/{control.robot_id}) until its places are found in the map")

    def on_session_stop(self, session_id: str) -> None:
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
        session.bytes_in += len(payload)
        session.final = session.final or message.final
        if opened.shared.submaps[message.robot_id].session != message.session_id:
            return  # an earlier session of the robot, still finishing: its keyframes are in the map already
        event = opened.shared.add(message.robot_id, KeyframeBatch(first=message.first, **arrays), message.camera)
        session.keyframes = len(opened.shared.submaps[message.robot_id])
        if event is not None:
            self._merged(opened, event)
        opened.work_s += time.thread_time() - began

    def process_one(self, timeout: float = 0.2) -> bool:
        handled = super().process_one(timeout)
        now = time.monotonic()
        for name, opened in list(self.maps.items()):
            if all(s.ended_at is not None and (s.final or now - s.ended_at > FINAL_WAIT_S)
                   for s in opened.sessions.values()):
                self._close(name, opened)
        return handled

    def _merged(self, opened: OpenMap, event: MergeEvent) -> None:
        """A robot placed in the map's frame: said on ``twohr/maps/<name>/merged`` and on its session's status."""
        name = opened.shared.name
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

    def _fetch(self, control: ControlMsg) -> MapFile | None:
        """The stored map a shared map starts from; None where the store has none of that name."""
        key = keys.map_key(control.map_name)
        for reply in self.session.get(key, timeout=STORE_TIMEOUT_S):
            if reply.ok is None:
                return None  # no such map yet: the first robot's frame will be its frame
            return read_map(reply.ok.payload.to_bytes(), detector=control.config.detector)
        raise TwohrError(f"map {control.map_name}: the map store did not answer on {key} (twohr up --maps DIR)")

    def _close(self, name: str, opened: OpenMap) -> None:
        """The map's last session ended: the map saved as its next version, robots that never merged as maps of
        their own; each session told its bytes."""
        del self.maps[name]
        for session_id in opened.sessions:
            self.sessions.pop(session_id, None)
        shared = opened.shared
        merged = [key for key in opened.merged_into if key in shared.submaps]
        first = next(s for s in opened.sessions.values())  # the session that opened the map saves it
        self._save(name, export(shared, merged), opened, first.control, "robots " + ", ".join(
            sorted({shared.submaps[k].robot for k in merged if k != STORED})))
        for key, submap in shared.submaps.items():
            if submap.T is None and len(submap):
                own = f"{name}.{submap.robot}"
                control = opened.sessions[submap.session].control
                if self._save(own, export(shared, [key]), opened, control, f"robot {submap.robot}"):
                    self.report(control, "not merged", f"robot {submap.robot}'s places were never found in map "
                                f"{name}: its {len(submap)} keyframes are saved as map {own}")
        self.log.info("map %s closed: %.2f s of this thread's CPU on its %d keyframes", name, opened.work_s,
                      sum(len(s) for s in shared.submaps.values()))
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
                                 built_by=f"shared map {opened.shared.name}: {built_by}",
                                 parent=None if opened.shared.stored is None else opened.shared.stored.header,
                                 cameras=exported.cameras[1:], camera_robots=exported.robots)
            payload = encode_map(stored)
        except MapFileError as exc:
            self.report(control, "error", f"map {name} not saved: {exc}")
            return False
        key = keys.map_key(name, save=True)
        for reply in self.session.get(key, payload=payload, attachment=control.session_id, timeout=STORE_TIMEOUT_S):
            if reply.ok is not None:
                self.report(control, "map saved", f"map {name}: {stored.header.keyframes} keyframes, "
                            f"{stored.header.landmarks} landmarks", keyframes=stored.header.keyframes,
                            landmarks=stored.header.landmarks)
                return True
            why = reply.err.payload.to_bytes().decode(errors="replace")
            self.report(control, "error", f"map {name} not saved: {why}")
            return False
        self.report(control, "error", f"map {name} not saved: the map store did not answer on {key}")
        return False


@one_line_errors("mapserver")
def main(argv: list[str] | None = None) -> None:
    parser = service_parser("mapserver", __doc__)
    args = parser.parse_args(argv)
    MapServerService(bus_from_args(args)).run_forever()
