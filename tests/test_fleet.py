"""A fleet's keys on a real Zenoh router (loopback): one identity per robot, mutual TLS, revocation while running,
and one clear line for every unusable key. The same across hosts, with the whole stack: test_fleet_hosts.py."""

from __future__ import annotations

import datetime
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from pydantic import SecretStr

from twohr.bus import BusConfig, free_port, open_session
from twohr.errors import TwohrError
from twohr.identity import Bundle, IdentityError, load_identity
from twohr_app.fleet import Fleet, FleetError, pem, reveal
from twohr_app.fleet_router import ACL_TARGET, DenialFilter, FleetRouter, parse_denial


def twohr(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def keys(tmp_path_factory) -> tuple[Fleet, dict[str, Path]]:
    folder = tmp_path_factory.mktemp("fleet") / "K"
    done = twohr("keys", "init", str(folder))
    assert done.returncode == 0, done.stderr
    fleet = Fleet(folder)
    bundles = {}
    for robot in ("a", "b", "c"):
        bundles[robot] = folder.parent / f"{robot}.bundle"
        done = twohr("keys", "add", str(folder), robot, "--out", str(bundles[robot]))
        assert done.returncode == 0, done.stderr
    return fleet, bundles


def test_keys_are_private_and_listed(keys):
    fleet, bundles = keys
    assert fleet.folder.stat().st_mode & 0o777 == 0o700
    for private in (fleet.folder / "ca.key", fleet.folder / "fleet.json", bundles["a"],
                    fleet.service_folder("tracker") / "key.pem", fleet.service_folder("router") / "users.txt"):
        assert private.stat().st_mode & 0o777 == 0o600, private
    a = load_identity(bundles["a"])
    assert a.name == "a" and a.api_token is not None and a.endpoint is None
    assert load_identity(fleet.service_folder("tracker")).name == "tracker"
    mounted = fleet.folder.parent / "mounted" / "keys"  # a container sees its folder at /run/twohr/keys
    shutil.copytree(fleet.service_folder("tracker"), mounted)
    assert load_identity(mounted).name == "tracker"
    listed = twohr("keys", "list", str(fleet.folder))
    assert listed.returncode == 0 and [line.split()[:2] for line in listed.stdout.splitlines()[1:4]] == [
        ["a", "active"], ["b", "active"], ["c", "active"]]
    again = twohr("keys", "add", str(fleet.folder), "a", "--out", str(fleet.folder.parent / "a2.bundle"))
    assert again.returncode == 2 and "already in the fleet" in again.stderr
    role = twohr("keys", "add", str(fleet.folder), "tracker", "--out", str(fleet.folder.parent / "t.bundle"))
    assert role.returncode == 2 and "a service role's name" in role.stderr and "Traceback" not in role.stderr


def _write(bundle: Bundle, path: Path) -> Path:
    path.write_text(json.dumps(reveal(bundle)))
    return path


def test_every_unusable_key_is_one_clear_line(keys, tmp_path, dev_sequence):
    fleet, bundles = keys
    a = load_identity(bundles["a"])
    cert, key = fleet.issue("old", days=1, not_before=datetime.datetime.now(datetime.timezone.utc)
                            - datetime.timedelta(days=3))
    expired = _write(a.model_copy(update={"name": "old", "cert_pem": pem(cert), "key_pem": SecretStr(pem(key))}),
                     tmp_path / "expired.bundle")
    other = Fleet(tmp_path / "other")
    other.init()
    foreign = other.add("a", tmp_path / "foreign.bundle")
    # a's certificate with another fleet's CA named as its issuer
    mixed = _write(foreign.model_copy(update={"cert_pem": a.cert_pem, "key_pem": a.key_pem}), tmp_path / "mixed.bundle")
    corrupt = tmp_path / "corrupt.bundle"
    corrupt.write_text(bundles["a"].read_text()[:300])
    no_key = tmp_path / "nokey"
    no_key.mkdir()
    for name in ("ca.crt", "cert.pem", "password"):
        (no_key / name).write_text((fleet.service_folder("tracker") / name).read_text())
    cases = {expired: "expired on", mixed: "not signed by the bundle's CA", corrupt: "not a twohr bundle",
             no_key: "lacks key.pem", tmp_path / "missing.bundle": "key file not found"}
    for path, reason in cases.items():
        with pytest.raises(IdentityError, match=reason):
            load_identity(path)
    for path, reason in list(cases.items())[:3]:  # and from the command line: one line, no traceback
        done = twohr("camera", "--keys", str(path), "--router", "tls/127.0.0.1:9", "--replay", str(dev_sequence),
                     "--frames", "1")
        assert done.returncode == 2 and reason in done.stderr, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    for service in ("tracker", "gateway"):  # the services too, at start, in a few seconds
        done = subprocess.run([sys.executable, "-m", f"twohr_services.{service}", "--keys", str(expired), "--router",
                               "tls/127.0.0.1:9"], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and done.stderr.strip().startswith(f"{service}: error: ") and \
            "expired on" in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr


def _client(bundle_or_identity, endpoint: str) -> zenoh.Session:
    identity = load_identity(bundle_or_identity) if isinstance(bundle_or_identity, Path) else bundle_or_identity
    return open_session(BusConfig(connect=[endpoint], identity=identity, user=None, password=None, config_file=None,
                                  shared_memory=False))


def test_one_identity_per_robot_and_revocation_while_running(keys, tmp_path, self_signed_bundle):
    fleet, bundles = keys
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = FleetRouter(fleet.service_folder("router"), [endpoint])
    sessions = []
    try:
        tracker = _client(fleet.identity("tracker"), endpoint)
        source = _client(fleet.identity("source"), endpoint)  # the service that takes cameras in
        got: list[tuple[float, str, bytes]] = []
        lock = threading.Lock()

        def on_frame(sample) -> None:
            with lock:
                got.append((time.monotonic(), str(sample.key_expr), sample.payload.to_bytes()))

        sessions += [tracker, source]
        source.declare_subscriber("twohr/*/camera", on_frame)
        a, b = _client(bundles["a"], endpoint), _client(bundles["b"], endpoint)
        sessions += [a, b]
        poses_at_a: list[str] = []
        a.declare_subscriber("twohr/*/pose", lambda s: poses_at_a.append(str(s.key_expr)))
        watched: list[str] = []
        tracker.liveliness().declare_subscriber("twohr/_alive/**", lambda s: watched.append(str(s.key_expr)))
        time.sleep(1.0)
        a.declare_publisher("twohr/a/camera").put(b"a's own")  # as a camera driver does
        b.declare_publisher("twohr/a/camera").put(b"b posing as a")
        b.put("twohr/b/camera", b"b's own")
        b.put("twohr/b/pose", b"b may not publish poses")
        token = b.liveliness().declare_token("twohr/_alive/detector/b")  # b may not pose as a service either
        tracker.put("twohr/b/pose", b"a pose")
        time.sleep(1.0)
        with lock:
            assert sorted((k, p) for _, k, p in got) == [("twohr/a/camera", b"a's own"), ("twohr/b/camera", b"b's own")]
        assert poses_at_a == ["twohr/b/pose"] and watched == []
        token.undeclare()
        # a map snapshot goes from the tracker to the map room only: a robot may neither send one nor ask for one,
        # and the gateway neither keeps nor serves one
        room, gateway = _client(fleet.identity("mapserver"), endpoint), _client(fleet.identity("gateway"), endpoint)
        sessions += [room, gateway]
        snapshots: list[tuple[str, str, bytes]] = []
        for name, who in (("mapserver", room), ("gateway", gateway)):
            who.declare_subscriber("twohr/*/map/snapshot", lambda s, n=name: snapshots.append(
                (n, str(s.key_expr), s.payload.to_bytes())))
            who.declare_queryable("twohr/*/map/snapshot", lambda q, n=name: q.reply(q.key_expr, f"{n}'s map".encode()))
        time.sleep(1.0)
        b.put("twohr/a/map/snapshot", b"b's forged map of a")
        b.put("twohr/b/map/snapshot", b"b's own map")
        tracker.put("twohr/a/map/snapshot", b"a's map")
        asked = {name: [r.ok.payload.to_bytes() for r in who.get("twohr/a/map/snapshot", timeout=2.0)
                        if r.ok is not None] for name, who in (("b", b), ("tracker", tracker))}
        time.sleep(1.0)
        assert snapshots == [("mapserver", "twohr/a/map/snapshot", b"a's map")], snapshots
        assert asked == {"b": [], "tracker": [b"mapserver's map"]}, asked
        # no certificate, a self-signed one named a, a's certificate with b's password: refused or powerless
        with pytest.raises(TwohrError, match="cannot join"):
            open_session(BusConfig(connect=[endpoint], identity=None, user="a", password=SecretStr("x"),
                                   config_file=None))
        with pytest.raises(TwohrError, match="cannot join"):
            _client(load_identity(self_signed_bundle("a", tmp_path / "evil.bundle")), endpoint)
        b_as_a = load_identity(bundles["a"]).model_copy(update={"password": load_identity(bundles["b"]).password})
        with pytest.raises(TwohrError, match="cannot join"):
            _client(b_as_a, endpoint)

        # revoke a while a and b both stream at 30 Hz
        stop = threading.Event()

        def stream(session: zenoh.Session, robot: str) -> None:
            i = 0
            while not stop.is_set():
                session.put(f"twohr/{robot}/camera", str(i).encode())
                i += 1
                time.sleep(1 / 30)

        threads = [threading.Thread(target=stream, args=(s, r), daemon=True) for s, r in ((a, "a"), (b, "b"))]
        for thread in threads:
            thread.start()
        time.sleep(1.0)
        revoked_at = time.monotonic()
        assert twohr("keys", "revoke", str(fleet.folder), "a").returncode == 0
        deadline = revoked_at + 10.0
        while router.restarts == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert router.restarts == 1 and router.robots == ["b", "c"]
        time.sleep(3.0)
        check_from = time.monotonic()
        poses_at_a.clear()
        tracker.put("twohr/b/pose", b"after")
        time.sleep(3.0)
        stop.set()
        for thread in threads:
            thread.join()
        with lock:
            from_a = [t for t, k, _ in got if k == "twohr/a/camera" and t >= check_from]
            from_b = sorted(t for t, k, _ in got if k == "twohr/b/camera" and t >= revoked_at - 1.0)
        assert from_a == [] and poses_at_a == []  # nothing of a's arrives, and a receives nothing
        gap = max(later - earlier for earlier, later in zip(from_b, from_b[1:], strict=False))
        assert gap < 2.0 and from_b[-1] > check_from + 2.5, gap  # b goes on, losing at most 2 s of frames
        with pytest.raises(TwohrError, match="cannot join"):  # and a's connection is refused outright
            _client(bundles["a"], endpoint)
    finally:
        for session in sessions:
            session.close()
        router.close()
    with pytest.raises(FleetError, match="no robot 'zz'"):
        fleet.revoke("zz")


def test_a_denial_line_names_the_identity_and_the_key():
    line = ("\x1b[2m2026-12-05T09:11:54Z\x1b[0m TRACE rx-1 zenoh::net::routing::interceptor::access_control: cf6d on "
            "Interface(lo)+CertCommonName(b)+Username(b)+Transport(Tls)+cf6d is unauthorized to Put (ingress) on "
            "twohr/a/camera")
    assert parse_denial(line) == ("b", "put", "twohr/a/camera")
    assert parse_denial(line.replace("(ingress)", "(egress)")) is None
    assert parse_denial("zenoh::net::routing::interceptor::access_control: x is authorized to Put on k") is None
    # what Zenoh logs when a client declares a key is permission caching, not a denial of anything it sent
    caching = [f"TRACE rx-0 ThreadId(08) {ACL_TARGET}: ACL (ingress): caching permissions for `twohr/_alive/x` ...",
               line.replace("rx-1", "rx-0 ThreadId(08)").replace("twohr/a/camera", "twohr/_alive/x"),
               f"TRACE rx-0 ThreadId(08) {ACL_TARGET}: y is authorized to Reply (ingress) on twohr/_alive/x",
               line.replace("rx-1", "rx-0 ThreadId(08)").replace("twohr/a/camera", "twohr/_alive/x"),
               f"TRACE rx-0 ThreadId(08) {ACL_TARGET}: y is authorized to Declare Subscriber (ingress) on twohr/b/pose",
               line.replace("rx-1", "rx-0 ThreadId(08)")]
    cached = (f"TRACE rx-1 ThreadId(09) {ACL_TARGET}: Using cached result: cf6d is unauthorized to Put (ingress) "
              "on twohr/a/camera")  # Zenoh names the client by its id alone once it has seen it
    one_log = DenialFilter()
    assert [one_log.denial(text) for text in [*caching, cached]] == [None] * 5 + [("b", "put", "twohr/a/camera")] * 2


def test_a_robots_own_router_carries_the_robots_identity(keys, tmp_path):
    """``twohr router --keys c.bundle``: the robot's processes join it on loopback with the same bundle, and what
    they publish reaches the stack as robot c's, so c's rules hold for all of it."""
    fleet, bundles = keys
    endpoint, local = f"tls/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    router = FleetRouter(fleet.service_folder("router"), [endpoint])
    robot_router = subprocess.Popen([sys.executable, "-m", "twohr_app", "router", "--keys", str(bundles["c"]),
                                     "--listen", local, "--connect", endpoint], stdout=subprocess.PIPE, text=True)
    sessions = []
    try:
        assert "of robot c listening on" in robot_router.stdout.readline()
        source = _client(fleet.identity("source"), endpoint)
        sessions.append(source)
        got: list[str] = []
        source.declare_subscriber("twohr/*/camera", lambda sample: got.append(str(sample.key_expr)))
        with pytest.raises(TwohrError, match="cannot join"):  # a process with nothing is not let in
            open_session(BusConfig(connect=[local], identity=None, user=None, password=None, config_file=None))
        on_robot = _client(bundles["c"], local)
        sessions.append(on_robot)
        time.sleep(1.5)
        on_robot.declare_publisher("twohr/c/camera").put(b"c's camera")
        on_robot.declare_publisher("twohr/a/camera").put(b"c's process posing as a")
        time.sleep(1.0)
        assert got == ["twohr/c/camera"]
        exposed = twohr("router", "--keys", str(bundles["c"]), "--listen", "tcp/0.0.0.0:1")
        assert exposed.returncode == 2 and "on loopback" in exposed.stderr
    finally:
        for session in sessions:
            session.close()
        robot_router.terminate()
        robot_router.wait(10)
        router.close()


def test_a_robot_reads_no_replica_or_host_of_the_services(keys):
    """The services' health answers and liveliness tokens name every replica and its host: a service (here the
    gateway, the tracker) reads them, a robot gets nothing of either, and ``twohr health`` with its bundle says only
    that the stack's router admits it."""
    from twohr.keys import alive_key, health_key

    fleet, bundles = keys
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = FleetRouter(fleet.service_folder("router"), [endpoint])
    sessions = []
    try:
        detector = _client(fleet.identity("detector"), endpoint)
        gateway, tracker, b = (_client(fleet.identity("gateway"), endpoint), _client(fleet.identity("tracker"),
                               endpoint), _client(bundles["b"], endpoint))
        sessions += [detector, gateway, tracker, b]
        replica = "gpu-host-1-detector"
        answer = json.dumps({"service": "detector", "replica": replica, "host": "gpu-host", "received": 7})
        queryable = detector.declare_queryable(health_key("detector", replica),
                                               lambda query: query.reply(health_key("detector", replica), answer))
        token = detector.liveliness().declare_token(alive_key("detector", replica))
        time.sleep(1.0)
        replies = {}
        for name, session in (("gateway", gateway), ("b", b)):
            replies[name] = [r.ok.payload.to_string() for r in session.get(health_key("detector"), timeout=2.0)
                             if r.ok]  # what twohr health asks
        tokens = {name: [str(r.ok.key_expr) for r in session.liveliness().get(alive_key("detector"), timeout=2.0)
                         if r.ok] for name, session in (("tracker", tracker), ("b", b))}
        watched: list[str] = []
        b.liveliness().declare_subscriber("twohr/_alive/**", lambda s: watched.append(str(s.key_expr)))
        time.sleep(0.5)
        token.undeclare()
        again = detector.liveliness().declare_token(alive_key("detector", "gpu-host-2-detector"))
        time.sleep(1.0)
        assert replies == {"gateway": [answer], "b": []}, replies
        assert tokens == {"tracker": [alive_key("detector", replica)], "b": []}, tokens
        assert watched == []
        again.undeclare()
        queryable.undeclare()
        done = twohr("health", "--keys", str(bundles["b"]), "--router", endpoint)
        assert done.returncode == 0 and f"the router at {endpoint} admits robot b" in done.stdout, done.stderr
        assert "gpu-host" not in done.stdout and "NOT ANSWERING" not in done.stdout
    finally:
        for session in sessions:
            session.close()
        router.close()
