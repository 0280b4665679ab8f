"""Maps are owned (issue 49, item 2) and audited (item 8), on real parts: a real Zenoh router carries the map
store's saves as the tracker sends them (the session's id attached), a real fleet's keys folder holds the robots'
tokens and the operator's grants, and ``twohr`` runs as a process. The whole story with a running stack and SLAM
sessions over HTTPS is tests/test_map_ownership.py."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import time
import zipfile

import pytest

from twohr import keys
from twohr.bus import open_session
from twohr.dataset import CameraIntrinsics
from twohr.mapfile import (
    OPERATOR,
    VERSION,
    MapAccessError,
    MapFileError,
    MapStore,
    encode_map,
    read_header,
    read_map,
)
from twohr_app.fleet import Fleet, FleetError
from twohr_services.gateway.audit import AuditLog, KeysWatch
from twohr_services.gateway.bus import GatewayBus
from twohr_services.gateway.ownership import Grants
from twohr_services.gateway.sessions import MapRequest, Session, SessionRequest, SessionTable
from twohr_services.gateway.settings import GatewaySettings

CAMERA = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)


def twohr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True, timeout=120)


def one_error_line(done: subprocess.CompletedProcess) -> str:
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    return lines[0]


def map_bytes(tiny_map, name: str, shift: float = 0.0) -> bytes:
    """A valid map file's bytes; ``shift`` moves its landmarks (another version's content)."""
    made = tiny_map(name, CAMERA)
    made.arrays.landmark_positions += shift
    return encode_map(made)


def as_version_1(data: bytes, **extra) -> bytes:
    """A map file as twohr wrote it before maps had owners: format version 1, no ``owners`` in its header (and
    ``extra`` fields in it, if given)."""
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as target:
        for member in source.infolist():
            content = source.read(member)
            if member.filename == "header.json":
                header = json.loads(content)
                del header["owners"]
                content = json.dumps({**header, "version": 1, **extra}).encode()
            target.writestr(member.filename, content)
    return out.getvalue()


def save(client, name: str, data: bytes, session: str | None = None):
    """One save on ``twohr/maps/<name>/save`` as the tracker sends it; its one reply."""
    replies = list(client.get(keys.map_key(name, save=True), payload=data, timeout=30,
                              **({"attachment": session} if session else {})))
    assert len(replies) == 1
    return replies[0]


def wait_for_store(client, name: str) -> None:
    """Until the gateway's map store answers on the bus (its queryable's route reached the router)."""
    deadline = time.monotonic() + 30
    while not list(client.get(keys.map_key(name), timeout=1.0)):
        assert time.monotonic() < deadline, "the gateway's map store never answered"


@pytest.fixture
def fleet(tmp_path) -> Fleet:
    """A real fleet's keys folder with robots a and b."""
    made = Fleet(tmp_path / "K")
    made.init()
    for robot in ("a", "b"):
        made.add(robot, tmp_path / f"{robot}.bundle")
    return made


def test_the_store_keeps_n_versions_numbered_as_they_were(bus_config, tmp_path, tiny_map):
    """N + 2 saves over the bus into a store that keeps N: the last N remain, under the numbers they were saved
    as, each with the bytes it was saved with; a rollback to a pruned version is a one-line 404-kind error."""
    keep, maps = 3, tmp_path / "maps"
    bus = GatewayBus(GatewaySettings(maps=maps, bus=bus_config, map_versions=keep, recordings=tmp_path / "rec"),
                     SessionTable())
    bus.start()
    client = open_session(bus_config)
    try:
        wait_for_store(client, "lab")
        served = {}
        for number in range(1, keep + 3):
            reply = save(client, "lab", map_bytes(tiny_map, "lab", shift=number))
            assert reply.ok is not None, reply.err.payload.to_string()
            assert json.loads(reply.ok.payload.to_bytes())["version"] == number
            served[number] = next(r.ok.payload.to_bytes() for r in client.get(keys.map_key("lab"), timeout=10))
            assert read_map(served[number]).arrays.landmark_positions[0, 0] == 1 + number
    finally:
        client.close()
        bus.close()
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


def test_a_version_1_map_still_loads_and_is_the_operators(tmp_path, tiny_map):
    old = as_version_1(map_bytes(tiny_map, "old"))
    (tmp_path / "old.map").write_bytes(old)
    header = read_header(tmp_path / "old.map")
    assert (header.version, header.owners) == (1, [OPERATOR])
    assert read_map(tmp_path / "old.map").arrays.landmark_positions.shape == (3, 3)
    store = MapStore(tmp_path)
    assert (store.entry("old").version, store.entry("old").owners) == (1, [OPERATOR])
    # a robot neither owns it nor is granted it: refused, nothing changes
    with pytest.raises(MapAccessError, match="owned by @operator"):
        store.save(map_bytes(tiny_map, "old", 1.0), builder="a", may_replace=lambda owners: "a" in owners)
    assert store.numbers("old") == [1] and (tmp_path / "old.map").read_bytes() == old
    # granted: its version is the next one, in the current format, still the operator's, a among its contributors;
    # version 1 is kept byte for byte
    entry = store.save(map_bytes(tiny_map, "old", 1.0), builder="a", may_replace=lambda owners: True)
    assert (entry.version, entry.owners, entry.contributors) == (2, [OPERATOR], ["a"])
    assert read_header(tmp_path / "old.map").version == VERSION
    assert store.version_path("old", 1).read_bytes() == old
    # a version-1 header that claims owners is not one twohr wrote
    claims = as_version_1(map_bytes(tiny_map, "odd"), owners=["a"])
    with pytest.raises(MapFileError, match="a version-1 map has no owners"):
        read_map(claims)


def test_a_tracker_save_records_its_sessions_robot_and_needs_its_rights(bus_config, tmp_path, tiny_map, fleet):
    """The map store on the bus, as the tracker saves at a session's end (the session's id attached): the session's
    robot owns a map it builds; another robot's session may not replace the map until the operator grants it, and
    is recorded as a contributor, not an owner: the grant taken back, it is refused again. A session the operator
    starts for a robot changes the map without making that robot an owner either."""
    maps, audit_file = tmp_path / "maps", tmp_path / "rec" / "audit.jsonl"
    settings = GatewaySettings(maps=maps, bus=bus_config, recordings=tmp_path / "rec",
                               robot_tokens=fleet.service_folder("gateway") / "tokens.json")
    table = SessionTable()
    audit = AuditLog(settings.audit_file())
    bus = GatewayBus(settings, table, audit, Grants(settings.grants_file()))

    def session(sid: str, robot: str, mode: str, started_by: str, name: str = "lab") -> str:
        table.add(Session(id=sid, request=SessionRequest(source="camera", robot_id=robot, record=False,
                                                         map=MapRequest(name=name, mode=mode)),
                          folder=None, started_by=started_by))
        return sid

    bus.start()
    client = open_session(bus_config)
    try:
        wait_for_store(client, "lab")
        built = save(client, "lab", map_bytes(tiny_map, "lab"), session("sa", "a", "build", "a"))
        assert built.ok is not None and json.loads(built.ok.payload.to_bytes())["owners"] == ["a"]
        first = (maps / "lab.map").read_bytes()

        refused = save(client, "lab", map_bytes(tiny_map, "lab", 1.0), session("sb", "b", "extend", "b"))
        assert refused.err is not None and "owned by a" in refused.err.payload.to_string()
        for sid, name in (("nobody", "lab"), ("sa", "other")):  # a session it does not know, or of another map
            stray = save(client, name, map_bytes(tiny_map, name, 2.0), sid)
            assert stray.err is not None and "no session of this gateway" in stray.err.payload.to_string()
        assert MapStore(maps).numbers("lab") == [1] and (maps / "lab.map").read_bytes() == first
        assert not (maps / "other.map").exists()

        fleet.grant("b", "lab")  # read by the gateway at its next save
        granted = save(client, "lab", map_bytes(tiny_map, "lab", 1.0), "sb")
        assert granted.ok is not None, granted.err.payload.to_string()
        entry = json.loads(granted.ok.payload.to_bytes())
        assert (entry["version"], entry["owners"], entry["contributors"]) == (2, ["a"], ["b"])
        fleet.grant("b", "lab", remove=True)  # the grant was the authority: taken back, b's next save is refused
        ungranted = save(client, "lab", map_bytes(tiny_map, "lab", 3.0), "sb")
        assert ungranted.err is not None and "owned by a" in ungranted.err.payload.to_string()
        # the operator starts an extend for b: accepted, and b still owns nothing
        by_operator = save(client, "lab", map_bytes(tiny_map, "lab", 4.0), session("sob", "b", "extend", OPERATOR))
        assert by_operator.ok is not None, by_operator.err.payload.to_string()
        assert MapStore(maps).owners("lab") == ["a"] and MapStore(maps).numbers("lab") == [1, 2, 3]
        assert save(client, "lab", map_bytes(tiny_map, "lab", 5.0), "sb").err is not None
        assert MapStore(maps).numbers("lab") == [1, 2, 3]
        # the operator's token may start a session for any robot on any map: its robot is recorded as builder
        for_c = save(client, "mine", map_bytes(tiny_map, "mine"), session("so", "c", "build", OPERATOR, "mine"))
        assert for_c.ok is not None and MapStore(maps).owners("mine") == ["c"]
        c_again = save(client, "mine", map_bytes(tiny_map, "mine", 1.0), session("sc", "b", "build", "b", "mine"))
        assert c_again.err is not None and "owned by c" in c_again.err.payload.to_string()
    finally:
        client.close()
        bus.close()
    assert audit_file.stat().st_mode & 0o777 == 0o600
    lines = [json.loads(line) for line in audit_file.read_text().splitlines()]
    saves = [(e["who"], e["robot"], e.get("version"), e["detail"].split(":")[0]) for e in lines
             if e["action"] == "map.save" and e["map"] == "lab"]
    assert saves == [("a", "a", 1, "owners a"), ("b", "b", None, "refused"), ("b", "b", 2, "owners a; contributors b"),
                     ("b", "b", None, "refused"), (OPERATOR, "b", 3, "owners a; contributors b"),
                     ("b", "b", None, "refused")]
    assert all(isinstance(e["time"], float) and e["utc"].endswith("+00:00") for e in lines)


def test_keys_grant_and_its_bad_input(fleet, tmp_path):
    grants = fleet.service_folder("gateway") / "grants.json"
    done = twohr("keys", "grant", str(fleet.folder), "b", "--map", "lab")
    assert done.returncode == 0 and "granted map lab" in done.stdout, done.stderr
    assert grants.stat().st_mode & 0o777 == 0o600
    assert list(json.loads(grants.read_text())["maps"]["lab"]) == ["b"]
    assert Grants(grants).current().allows("b", "lab") and not Grants(grants).current().allows("a", "lab")
    for args, says in ((["zz", "--map", "lab"], "no active robot 'zz'"),
                       (["b", "--map", "../lab"], "is not a map name"),
                       (["b", "--map", "lab.v2"], "is not a map name"),
                       (["a", "--map", "lab", "--remove"], "holds no grant on map 'lab'")):
        assert says in one_error_line(twohr("keys", "grant", str(fleet.folder), *args))
    assert list(json.loads(grants.read_text())["maps"]) == ["lab"]  # the refusals changed nothing
    assert twohr("keys", "grant", str(fleet.folder), "b", "--map", "lab", "--remove").returncode == 0
    assert json.loads(grants.read_text())["maps"] == {} and not Grants(grants).current().allows("b", "lab")
    with pytest.raises(FleetError, match="holds no grant"):
        fleet.grant("b", "lab", remove=True)


def test_the_audit_trail_notices_grants_and_revocations_made_while_no_stack_ran(fleet, tmp_path):
    tokens = fleet.service_folder("gateway") / "tokens.json"
    audit = AuditLog(tmp_path / "rec" / "audit.jsonl")
    first = KeysWatch(audit, tokens, fleet.service_folder("gateway") / "grants.json")
    first.poll()  # the first start: where the trail begins, nothing logged
    assert audit.read() == []
    fleet.grant("a", "lab")
    first.poll()
    assert [(e.action, e.robot, e.map) for e in audit.read()] == [("map.grant", "a", "lab")]
    # the stack stops; the operator grants b and revokes a; the next start logs both
    fleet.grant("b", "hall")
    fleet.revoke("a")
    again = KeysWatch(audit, tokens, fleet.service_folder("gateway") / "grants.json")
    again.poll()
    events = audit.read()
    assert [(e.action, e.who, e.robot, e.map) for e in events[1:]] == [
        ("robot.revoke", OPERATOR, "a", None), ("map.grant", OPERATOR, "b", "hall")]
    assert events[1].time >= events[0].time and "granted at" in events[2].detail
    again.poll()  # nothing changed since: nothing more
    assert len(audit.read()) == 3


def test_the_audit_trail_sees_a_token_replaced_and_a_replica_revoked(fleet, tmp_path):
    """A robot revoked and added again between two looks (the same name in the tokens file, another token's digest)
    is logged as both; a service replica of another host revoked (the router's robots.json) is logged too; a trail
    that knew the robots by name only logs nothing for them."""
    gateway = fleet.service_folder("gateway")
    audit = AuditLog(tmp_path / "rec" / "audit.jsonl")
    fleet.add_service("detector", "gpu-1", tmp_path / "replica")
    watch = KeysWatch(audit, gateway / "tokens.json", gateway / "grants.json")
    watch.poll()  # where the trail begins
    fleet.revoke("a")
    fleet.add("a", tmp_path / "a-again.bundle")
    fleet.revoke("detector@gpu-1")
    watch.poll()
    assert [(e.action, e.who, e.robot) for e in audit.read()] == [
        ("robot.revoke", OPERATOR, "a"), ("robot.add", OPERATOR, "a"), ("robot.revoke", OPERATOR, "detector@gpu-1")]
    watch.poll()
    assert len(audit.read()) == 3
    # a seen file from before digests: robots by name, no replicas
    (tmp_path / "rec" / ".audit-seen.json").write_text(json.dumps({"robots": ["a", "b"], "grants": {}}))
    KeysWatch(audit, gateway / "tokens.json", gateway / "grants.json").poll()
    assert len(audit.read()) == 3


def test_twohr_maps_rollback_on_the_folder(tmp_path, tiny_map):
    maps, audit_file = tmp_path / "maps", tmp_path / "rec" / "audit.jsonl"
    store = MapStore(maps)
    for shift in range(3):
        store.save(map_bytes(tiny_map, "lab", shift), builder="a")
    first = store.version_path("lab", 1).read_bytes()
    done = twohr("maps", "rollback", "lab", "--version", "1", "--maps", str(maps), "--audit", str(audit_file))
    assert done.returncode == 0 and "version 4 is version 1 again" in done.stdout, done.stderr
    assert (maps / "lab.map").read_bytes() == first and store.numbers("lab") == [1, 2, 3, 4]
    assert audit_file.stat().st_mode & 0o777 == 0o600
    logged = [json.loads(line) for line in audit_file.read_text().splitlines()]
    assert [(e["action"], e["who"], e["map"], e["version"]) for e in logged] == [
        ("map.rollback", OPERATOR, "lab", 4)]
    for args, says in ((["--version", "9"], "has no version 9"),
                       (["--version", "4"], "already the latest of map 'lab'"),
                       (["--version", "1", "--map-versions", "0"], "at least one version")):
        assert says in one_error_line(twohr("maps", "rollback", "lab", "--maps", str(maps), "--audit",
                                            str(audit_file), *args))
    assert "is not a map name" in one_error_line(twohr("maps", "rollback", "../lab", "--version", "1", "--maps",
                                                       str(maps), "--audit", str(audit_file)))
    assert store.numbers("lab") == [1, 2, 3, 4] and len(audit_file.read_text().splitlines()) == 1
