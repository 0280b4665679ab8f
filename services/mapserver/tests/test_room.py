"""The map room on a real Zenoh router: the map store's reads and saves (``twohr/maps/<name>``, ``.../save``), each
save checked against the session that built it as the room heard its start, and audited; the sessions' map
snapshots for a tracker move; how often each map was read. The other end is :class:`twohr.mapclient.MapClient`,
as the trackers use it, or plain queries where the test needs the raw reply.

A save that waits on the store is made deterministic rather than slow: the test holds the store's lock (the one a
save takes while another upload or save is under way), so the save cannot finish until the test lets it."""

from __future__ import annotations

import contextlib
import datetime
import json
import threading
import time

import pytest

from twohr import keys
from twohr.bus import open_session, query_health
from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics
from twohr.mapclient import NO_SNAPSHOT, MapClient, MapRoomUnreachable
from twohr.mapfile import OPERATOR, MapFileError, encode_map, read_map
from twohr.mapmodes import MapMode
from twohr.mapstore import _STORE_LOCK, MapAccessError, MapGrants, MapMissingError, MapStore
from twohr.messages import ControlMsg, encode
from twohr.service import declare_publisher
from twohr_app.fleet import Fleet
from twohr_services.mapserver.room import MapRoom, MapRoomSettings
from twohr_services.mapserver.service import MapServerService, build_parser, settings_from_args

CAMERA = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)


def map_bytes(tiny_map, name: str, shift: float = 0.0) -> bytes:
    """A valid map file's bytes; ``shift`` moves its landmarks (another version's content)."""
    made = tiny_map(name, CAMERA)
    made.arrays.landmark_positions += shift
    return encode_map(made)


@contextlib.contextmanager
def running(bus_config, settings: MapRoomSettings):
    """A map room serving ``settings`` on the router, until the block ends; yields (service, client session)."""
    service = MapServerService(bus_config, settings)
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), daemon=True)
    thread.start()
    client = open_session(bus_config)
    try:
        deadline = time.monotonic() + 30
        while query_health(client, "mapserver", timeout=1.0) is None:  # its queryables are declared before
            assert time.monotonic() < deadline, "the map room never answered"
        yield service, client
    finally:
        client.close()
        stop.set()
        thread.join(30)
        assert not thread.is_alive(), "the map room did not stop"


class Gateway:
    """Starts and stops sessions on the bus as the gateway does (its control messages), and waits until the map
    room has heard them."""

    def __init__(self, client, room: MapServerService) -> None:
        self.client, self.room = client, room
        self.publishers: dict[str, object] = {}

    def control(self, session_id: str, robot: str, command: str, mode: MapMode = MapMode.NONE, name: str = "",
                started_by: str = OPERATOR) -> str:
        key = keys.key(robot, keys.CONTROL)
        if key not in self.publishers:
            self.publishers[key] = declare_publisher(self.client, key)
        self.publishers[key].put(encode(ControlMsg(
            session_id=session_id, robot_id=robot, frame_index=-1, stamp=time.time(), command=command,
            map_name=name, map_mode=mode, started_by=started_by, config=PipelineConfig())))
        book = self.room.room.sessions
        deadline = time.monotonic() + 20
        while book.control(session_id) is None if command == "start" else book.active(session_id):
            assert time.monotonic() < deadline, f"the map room did not hear {command} of {session_id}"
            time.sleep(0.02)
        return session_id


def raw_save(client, name: str, data: bytes, session: str | None = None):
    """One save on ``twohr/maps/<name>/save`` as the tracker sends it; its one reply."""
    replies = list(client.get(keys.map_key(name, save=True), payload=data, timeout=30,
                              **({"attachment": session} if session else {})))
    assert len(replies) == 1
    return replies[0]


@pytest.fixture
def fleet(tmp_path) -> Fleet:
    """A real fleet's keys folder with robots a and b."""
    made = Fleet(tmp_path / "K")
    made.init()
    for robot in ("a", "b"):
        made.add(robot, tmp_path / f"{robot}.bundle")
    return made


def test_a_save_waiting_on_the_store_holds_up_no_other_map_query(bus_config, tmp_path, tiny_map):
    """Zenoh hands a queryable's queries to one callback thread, one after the other: a save doing its file I/O
    there kept every later save waiting (a refused one included), and a full channel would stall the session."""
    maps = tmp_path / "maps"
    MapStore(maps).save(map_bytes(tiny_map, "lab"), builder=OPERATOR)
    data = (maps / "lab.map").read_bytes()
    with running(bus_config, MapRoomSettings(maps=maps)) as (_, client):
        with _STORE_LOCK:  # another save is under way: this one must wait for it
            saving = client.get(keys.map_key("lab", save=True), payload=data, timeout=120)
            # sent after the save, on the same link: they reach the map room after it
            refused = raw_save(client, "lab", b"not a map")
            assert refused.err is not None, "a bad save waited for a save in progress"
            assert "not a twohr map" in refused.err.payload.to_string()
            assert MapClient(client, timeout=20).fetch("lab").header == read_map(data).header, \
                "a map read waited for a save in progress"
            assert saving.try_recv() is None, "the save finished while the store was locked"
        replies = list(saving)  # the lock is free: the save goes through and is answered
    assert len(replies) == 1 and replies[0].ok is not None, [r.err.payload.to_string() for r in replies if r.err]
    entry = json.loads(replies[0].ok.payload.to_bytes())
    assert entry["name"] == "lab" and entry["version"] == 2
    assert MapStore(maps).versions("lab") == [maps / "lab.v1.map"]


def test_the_client_reads_saves_and_is_told_why_not_and_each_read_is_counted(bus_config, tmp_path, tiny_map):
    """A missing map, a bad save, a name that is no map's: each one line, through the client as the tracker reads
    them; the room's health counts the reads of each map it served. With no map room, the client says so."""
    maps = tmp_path / "maps"
    with running(bus_config, MapRoomSettings(maps=maps)) as (_, client):
        store = MapClient(client, timeout=20)
        assert store.fetch("lab", optional=True) is None  # a shared map not stored yet
        with pytest.raises(MapMissingError, match="no map named 'lab'"):
            store.fetch("lab")
        entry = store.save(read_map(map_bytes(tiny_map, "lab")))  # no session: the operator's
        assert (entry.name, entry.version, entry.owners) == ("lab", 1, [OPERATOR])
        for _ in range(3):
            assert store.fetch("lab").header.name == "lab"
        with pytest.raises(MapFileError, match="is not a map name"):
            store.fetch("lab.v1")
        refused = raw_save(client, "lab", b"not a map")
        assert refused.err is not None and "not a twohr map" in refused.err.payload.to_string()
        health = query_health(client, "mapserver", timeout=5.0)
    assert health["reads"] == {"lab": 3}, health  # what the store did not have, or refused, is no read
    assert MapStore(maps).numbers("lab") == [1]
    alone = open_session(bus_config)  # the map room has stopped: nothing answers
    try:
        with pytest.raises(MapRoomUnreachable, match="the map room did not answer on twohr/maps/lab"):
            MapClient(alone, timeout=1.0).fetch("lab")
    finally:
        alone.close()


def test_the_store_keeps_n_versions_numbered_as_they_were(bus_config, tmp_path, tiny_map):
    """N + 2 saves over the bus into a store that keeps N: the last N remain, under the numbers they were saved
    as, each with the bytes it was saved with; a rollback to a pruned version is a one-line 404-kind error."""
    keep, maps = 3, tmp_path / "maps"
    served = {}
    with running(bus_config, MapRoomSettings(maps=maps, map_versions=keep)) as (_, client):
        for number in range(1, keep + 3):
            reply = raw_save(client, "lab", map_bytes(tiny_map, "lab", shift=number))
            assert reply.ok is not None, reply.err.payload.to_string()
            assert json.loads(reply.ok.payload.to_bytes())["version"] == number
            served[number] = next(r.ok.payload.to_bytes() for r in client.get(keys.map_key("lab"), timeout=10))
            assert read_map(served[number]).arrays.landmark_positions[0, 0] == 1 + number
    store = MapStore(maps, keep)
    assert store.numbers("lab") == [3, 4, 5]
    assert sorted(p.name for p in maps.glob("lab*")) == ["lab.map", "lab.v3.map", "lab.v4.map", "lab.v5.map"]
    for number in (3, 4, 5):
        assert store.version_path("lab", number).read_bytes() == served[number]
    assert (maps / "lab.map").read_bytes() == served[5]
    entry = store.entry("lab")
    assert (entry.version, entry.versions, entry.owners) == (5, [3, 4, 5], [OPERATOR])  # saves with no session
    with pytest.raises(MapFileError, match="has no version 1 \\(kept: 3, 4, 5\\)"):
        store.rollback("lab", 1)


def test_a_tracker_save_is_checked_against_the_session_start_the_room_heard(bus_config, tmp_path, tiny_map, fleet):
    """The saves as the tracker sends them at a session's end (the session's id attached), checked against the
    session's control message alone: the session's robot owns a map it builds; another robot's session may not
    replace the map until the operator grants it (``twohr keys grant``, which the room reads at each save), and is
    recorded as a contributor, not an owner: the grant taken back, it is refused again. A session the operator starts
    for a robot changes the map without making that robot an owner either. A session that does not save that map,
    or that the room never heard of, saves nothing. Every save and every refusal on rights is in the audit trail."""
    maps, audit_file = tmp_path / "maps", tmp_path / "maps" / "audit.jsonl"
    grants = fleet.service_folder("mapserver") / "grants.json"
    settings = MapRoomSettings(maps=maps, map_grants=grants)
    assert settings.audit_file() == audit_file  # the stack's one trail, in the store's folder
    with running(bus_config, settings) as (room, client):
        gateway = Gateway(client, room)
        built = raw_save(client, "lab", map_bytes(tiny_map, "lab"),
                         gateway.control("sa", "a", "start", MapMode.BUILD, "lab", started_by="a"))
        assert built.ok is not None and json.loads(built.ok.payload.to_bytes())["owners"] == ["a"]
        first = (maps / "lab.map").read_bytes()

        gateway.control("sb", "b", "start", MapMode.EXTEND, "lab", started_by="b")
        gateway.control("sb", "b", "stop")  # the tracker saves after the end: the room still knows the session
        refused = raw_save(client, "lab", map_bytes(tiny_map, "lab", 1.0), "sb")
        assert refused.err is not None and "owned by a" in refused.err.payload.to_string()
        gateway.control("sl", "b", "start", MapMode.LOCALIZE, "lab", started_by="b")
        for sid, name in (("nobody", "lab"), ("sa", "other"), ("sl", "lab")):  # unknown, another map, no save
            stray = raw_save(client, name, map_bytes(tiny_map, name, 2.0), sid)
            assert stray.err is not None and "no session of the map room" in stray.err.payload.to_string()
        assert MapStore(maps).numbers("lab") == [1] and (maps / "lab.map").read_bytes() == first
        assert not (maps / "other.map").exists()

        fleet.grant("b", "lab")  # into the gateway's and the map room's folders
        assert grants.is_file()
        granted = raw_save(client, "lab", map_bytes(tiny_map, "lab", 1.0), "sb")
        assert granted.ok is not None, granted.err.payload.to_string()
        entry = json.loads(granted.ok.payload.to_bytes())
        assert (entry["version"], entry["owners"], entry["contributors"]) == (2, ["a"], ["b"])
        fleet.grant("b", "lab", remove=True)  # the grant was the authority: taken back, b's next save is refused
        ungranted = raw_save(client, "lab", map_bytes(tiny_map, "lab", 3.0), "sb")
        assert ungranted.err is not None and "owned by a" in ungranted.err.payload.to_string()
        # the operator starts an extend for b: accepted, and b still owns nothing
        by_operator = raw_save(client, "lab", map_bytes(tiny_map, "lab", 4.0),
                               gateway.control("sob", "b", "start", MapMode.EXTEND, "lab"))
        assert by_operator.ok is not None, by_operator.err.payload.to_string()
        assert MapStore(maps).owners("lab") == ["a"] and MapStore(maps).numbers("lab") == [1, 2, 3]
        assert raw_save(client, "lab", map_bytes(tiny_map, "lab", 5.0), "sb").err is not None
        assert MapStore(maps).numbers("lab") == [1, 2, 3]
        # the operator's token may start a session for any robot on any map: its robot is recorded as builder
        for_c = raw_save(client, "mine", map_bytes(tiny_map, "mine"),
                         gateway.control("so", "c", "start", MapMode.BUILD, "mine"))
        assert for_c.ok is not None and MapStore(maps).owners("mine") == ["c"]
        c_again = raw_save(client, "mine", map_bytes(tiny_map, "mine", 1.0),
                           gateway.control("sc", "b", "start", MapMode.BUILD, "mine", started_by="b"))
        assert c_again.err is not None and "owned by c" in c_again.err.payload.to_string()
    assert audit_file.stat().st_mode & 0o777 == 0o600
    lines = [json.loads(line) for line in audit_file.read_text().splitlines()]
    saves = [(e["who"], e["robot"], e["session"], e.get("version"), e["detail"].split(":")[0]) for e in lines
             if e["action"] == "map.save" and e["map"] == "lab"]
    assert saves == [("a", "a", "sa", 1, "owners a"), ("b", "b", "sb", None, "refused"),
                     ("b", "b", "sb", 2, "owners a; contributors b"), ("b", "b", "sb", None, "refused"),
                     (OPERATOR, "b", "sob", 3, "owners a; contributors b"), ("b", "b", "sb", None, "refused")]
    assert all(isinstance(e["time"], float) and e["utc"].endswith("+00:00") for e in lines)


def test_a_live_sessions_snapshot_is_kept_for_its_next_tracker_and_goes_with_its_end(bus_config, tmp_path, tiny_map):
    """The tracker's snapshots of an active session's map: the latest is served for that session's robot and id
    alone (a move's new tracker asks), none for another session or robot, none once the session ended. The room
    keeps snapshots with no map store too (and then answers no map query)."""
    with running(bus_config, MapRoomSettings()) as (room, client):
        gateway = Gateway(client, room)
        tracker = MapClient(client, timeout=10)
        gateway.control("s1", "r1", "start")
        gateway.control("s2", "r2", "start")
        first, latest = tiny_map("lab", CAMERA), tiny_map("lab", CAMERA)
        latest.arrays.landmark_positions += 7
        tracker.send_snapshot("r1", "s1", first)
        tracker.send_snapshot("r1", "s1", latest)
        tracker.send_snapshot("r1", "s2", first)  # s2 is r2's: not kept under r1
        deadline = time.monotonic() + 10
        while room.room.sessions.snapshot("r1", "s1") != encode_map(latest):
            assert time.monotonic() < deadline, "the snapshot never reached the map room"
            time.sleep(0.02)
        moved = tracker.fetch_snapshot("r1", "s1")
        assert (moved.arrays.landmark_positions == 8).all()
        for robot, session in (("r2", "s2"), ("r1", "s2"), ("r2", "s1")):
            with pytest.raises(MapFileError, match=NO_SNAPSHOT):
                tracker.fetch_snapshot(robot, session)
        assert query_health(client, "mapserver", timeout=5.0)["snapshots"] == 1
        gateway.control("s1", "r1", "stop")
        with pytest.raises(MapFileError, match=NO_SNAPSHOT):
            tracker.fetch_snapshot("r1", "s1")
        # a robot runs one session at a time: a new start of r2 ends its earlier one, whose stop never came here
        tracker.send_snapshot("r2", "s2", first)
        deadline = time.monotonic() + 10
        while room.room.sessions.snapshot("r2", "s2") is None:
            assert time.monotonic() < deadline, "the snapshot never reached the map room"
            time.sleep(0.02)
        gateway.control("s3", "r2", "start")
        assert not room.room.sessions.active("s2") and room.room.sessions.snapshots() == 0
        assert not list(client.get(keys.map_key("lab", save=True), payload=encode_map(first), timeout=1.0))


def test_a_share_start_reads_the_stored_map_once_in_the_room(bus_config, tmp_path, tiny_map):
    """A session that shares a stored map: the room opens the shared map from its store (one read), the session's
    tracker fetches it over the bus (one more): each service that needs the map reads it once."""
    maps = tmp_path / "maps"
    MapStore(maps).save(map_bytes(tiny_map, "lab"), builder=OPERATOR)
    with running(bus_config, MapRoomSettings(maps=maps)) as (room, client):
        Gateway(client, room).control("s1", "a", "start", MapMode.SHARE, "lab")
        deadline = time.monotonic() + 20
        while "lab" not in room.maps:
            assert time.monotonic() < deadline, "the shared map was not opened"
            time.sleep(0.02)
        assert room.room.read_counts() == {"lab": 1}
        MapClient(client).fetch("lab")  # the tracker's
        assert query_health(client, "mapserver", timeout=5.0)["reads"] == {"lab": 2}


def test_the_command_line_and_its_one_line_errors(tmp_path):
    args = build_parser().parse_args(["--maps", str(tmp_path), "--map-versions", "3", "--map-grants",
                                      str(tmp_path / "g.json")])
    settings = settings_from_args(args)
    assert (settings.maps, settings.map_versions, settings.audit_file()) == (tmp_path, 3, tmp_path / "audit.jsonl")
    assert settings_from_args(build_parser().parse_args([])).audit_file() is None
    with pytest.raises(Exception, match="invalid settings: map_versions"):
        settings_from_args(build_parser().parse_args(["--map-versions", "0"]))


def test_the_grants_are_read_at_each_save_and_an_unreadable_file_grants_nothing(tmp_path, tiny_map):
    grants = tmp_path / "grants.json"
    grants.write_text("{not json")
    with pytest.raises(MapFileError, match="not the operator's map grants"):
        MapGrants.load(grants)
    assert MapGrants.load(tmp_path / "none.json") == MapGrants() == MapGrants.load(None)
    room = MapRoom(MapRoomSettings(maps=tmp_path / "maps", map_grants=grants))
    assert room.save(map_bytes(tiny_map, "lab"), "lab", None).owners == [OPERATOR]
    room.sessions.started(ControlMsg(session_id="sa", robot_id="a", frame_index=-1, stamp=0.0, command="start",
                                     map_name="lab", map_mode=MapMode.EXTEND, started_by="a"))
    with pytest.raises(MapAccessError, match="owned by @operator"):
        room.save(map_bytes(tiny_map, "lab", 1.0), "lab", "sa")
    grants.write_text(MapGrants(maps={"lab": {"a": datetime.datetime.now(datetime.timezone.utc)}}).model_dump_json())
    entry = room.save(map_bytes(tiny_map, "lab", 1.0), "lab", "sa")
    assert (entry.version, entry.owners, entry.contributors) == (2, [OPERATOR], ["a"])
    assert room.read_counts() == {}  # saves are no reads
