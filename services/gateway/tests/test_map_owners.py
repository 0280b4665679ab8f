"""Maps are owned (issue 49, item 2) and audited (item 8), on real parts: a real fleet's keys folder holds the
robots' tokens and the operator's grants, and ``twohr`` runs as a process. The saves on the bus, checked against the
session that built the map, are the map room's (services/mapserver/tests/test_room.py); the whole story with a
running stack and SLAM sessions over HTTPS is tests/test_map_ownership.py."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile

import pytest

from twohr.audit import AuditLog
from twohr.dataset import CameraIntrinsics
from twohr.mapfile import OPERATOR, VERSION, MapFileError, encode_map, read_header, read_map
from twohr.mapstore import MapAccessError, MapStore
from twohr_app.fleet import Fleet, FleetError
from twohr_services.gateway.audit import KeysWatch
from twohr_services.gateway.ownership import Grants

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


@pytest.fixture
def fleet(tmp_path) -> Fleet:
    """A real fleet's keys folder with robots a and b."""
    made = Fleet(tmp_path / "K")
    made.init()
    for robot in ("a", "b"):
        made.add(robot, tmp_path / f"{robot}.bundle")
    return made


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


def test_keys_grant_and_its_bad_input(fleet, tmp_path):
    grants = fleet.service_folder("gateway") / "grants.json"
    copy = fleet.service_folder("mapserver") / "grants.json"  # the map room checks a save with its own
    done = twohr("keys", "grant", str(fleet.folder), "b", "--map", "lab")
    assert done.returncode == 0 and "granted map lab" in done.stdout, done.stderr
    assert grants.stat().st_mode & 0o777 == 0o600 and copy.stat().st_mode & 0o777 == 0o600
    assert copy.read_bytes() == grants.read_bytes()
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
    assert copy.read_bytes() == grants.read_bytes()
    with pytest.raises(FleetError, match="holds no grant"):
        fleet.grant("b", "lab", remove=True)


def test_keys_made_before_the_map_room_read_grants_give_it_a_copy(fleet):
    """A keys folder whose grants only the gateway's folder holds (made before the map room checked saves):
    ``keys init --if-absent`` (compose's first step) gives the map room the same file; ``twohr up`` does too."""
    fleet.grant("b", "lab")
    copy = fleet.service_folder("mapserver") / "grants.json"
    copy.unlink()
    assert fleet.share_grants() and copy.read_bytes() == (fleet.service_folder("gateway") / "grants.json").read_bytes()
    copy.unlink()
    done = twohr("keys", "init", str(fleet.folder), "--if-absent")
    assert done.returncode == 0, done.stderr
    assert copy.read_bytes() == (fleet.service_folder("gateway") / "grants.json").read_bytes()
    assert copy.stat().st_mode & 0o777 == 0o600 and not fleet.share_grants()  # the same already: nothing written


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
