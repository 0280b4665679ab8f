"""Revocation that says so when it fails, short-lived robot certificates, and ``twohr keys`` input that is refused in
one line, with real processes: ``twohr keys`` and ``twohr router`` as a stack runs them, robots on real sessions.

- ``keys revoke`` waits for the running router to acknowledge the new list; with none running, or a list the router
  cannot open with (it then reopens with the old one and says why), it exits non-zero with one line;
- ``keys add`` and ``keys revoke`` from two processes at once lose nothing (the keys folder's lock);
- a robot whose certificate expires mid-session is cut by the router (``close_link_on_expiration``) within
  :data:`EXPIRY_CUT_S` of its expiry: measured at about 0.01 s on loopback (the last put of a 50 Hz stream arrives
  within one period of the certificate's ``notAfter``), with a margin for a loaded machine.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from cryptography import x509

from twohr.bus import BusConfig, free_port, open_session
from twohr.errors import TwohrError
from twohr.identity import IdentityError, load_identity
from twohr_app.fleet import Fleet, read_users, write_private
from twohr_app.fleet_router import APPLIED_FILE, Applied

#: the longest a robot whose certificate expired may still be heard (s): measured ~0.01 s, plus a margin
EXPIRY_CUT_S = 1.0


def twohr(*args: str, timeout: float = 90) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True, timeout=timeout)


def one_line_error(done: subprocess.CompletedProcess, code: int = 2) -> str:
    """The one line a refused command printed (and nothing else: no traceback)."""
    assert done.returncode == code, (done.returncode, done.stdout, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    return lines[0]


@pytest.fixture
def keys(tmp_path) -> Fleet:
    fleet = Fleet(tmp_path / "K")
    fleet.init()
    for robot in ("a", "b", "c"):
        fleet.add(robot, tmp_path / f"{robot}.bundle")
    return fleet


class Router:
    """``twohr router --keys K/services/router`` in its own process, as the compose file runs the stack's router."""

    def __init__(self, fleet: Fleet, log: Path) -> None:
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        self.log = log
        with open(log, "w") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "twohr_app", "router", "--keys",
                                          str(fleet.service_folder("router")), "--listen", self.endpoint],
                                         stdout=out, stderr=subprocess.STDOUT, text=True,
                                         env=os.environ | {"PYTHONUNBUFFERED": "1"})
        self.wait_for("zenoh router listening", 60)

    def wait_for(self, text: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while text not in (out := self.log.read_text()):
            assert self.proc.poll() is None and time.monotonic() < deadline, out
            time.sleep(0.05)
        return out

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(15)


def join(identity, endpoint: str) -> zenoh.Session:
    return open_session(BusConfig(connect=[endpoint], identity=identity, user=None, password=None, config_file=None,
                                  shared_memory=False))


class Stream:
    """A robot putting on its camera key at 50 Hz, and the source (the stack's service that takes cameras in)
    noting when each put arrives."""

    def __init__(self, source: zenoh.Session, robot: zenoh.Session, name: str) -> None:
        self.arrivals: list[float] = []
        self.name = name
        source.declare_subscriber(f"twohr/{name}/camera", lambda _: self.arrivals.append(time.time()))
        self._robot, self._stop = robot, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._robot.put(f"twohr/{self.name}/camera", b"frame")
            except zenoh.ZError:  # its session closed (a failed test's cleanup)
                return
            time.sleep(0.02)

    def since(self, t: float) -> int:
        return sum(1 for arrival in list(self.arrivals) if arrival >= t)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def test_keys_input_is_refused_in_one_line(keys, tmp_path):
    out = tmp_path / "x.bundle"
    for days in ("nan", "inf", "-inf", "0", "-1", "1e9", "3651"):
        line = one_line_error(twohr("keys", "add", str(keys.folder), "x", "--out", str(out), f"--days={days}"))
        assert "--days" in line and not out.exists(), line
    for endpoint in ("tcp/10.0.0.1:7447", "tcp/127.0.0.1:7447", "udp/10.0.0.1:7447", "tls/host", "10.0.0.1:7447"):
        line = one_line_error(twohr("keys", "add", str(keys.folder), "x", "--out", str(out), "--endpoint", endpoint))
        assert "tls/HOST:PORT" in line and not out.exists(), line
    folder = tmp_path / "a-folder"
    folder.mkdir()
    assert "is a folder" in one_line_error(twohr("keys", "add", str(keys.folder), "x", "--out", str(folder)))
    line = one_line_error(twohr("keys", "renew", str(keys.folder), "a", "--out", str(out), "--days", "nan"))
    assert "--days" in line
    assert "x" not in keys.read().robots
    # a bundle's password crosses no plain link to another host; on loopback it joins the robot's own router
    line = one_line_error(twohr("health", "--keys", str(tmp_path / "a.bundle"), "--router", "tcp/192.0.2.1:7447",
                                "--bus-only", "--timeout", "1"))
    assert "tls/HOST:PORT only" in line, line
    with pytest.raises(TwohrError, match="in clear"):
        join(load_identity(tmp_path / "a.bundle"), "tcp/192.0.2.1:7447")
    # a name is not loopback because it starts with 127.: it resolves wherever its owner says
    with pytest.raises(TwohrError, match="in clear"):
        join(load_identity(tmp_path / "a.bundle"), "tcp/127.attacker.example:7447")
    line = one_line_error(twohr("router", "--keys", str(tmp_path / "a.bundle"), "--listen",
                                "tcp/127.attacker.example:7447", "--connect", "tls/127.0.0.1:9"))
    assert "on loopback" in line, line
    # the stack's router on a fleet's keys listens on tls/ only, said before anything starts
    line = one_line_error(twohr("up", "--keys", str(keys.folder), "--router", f"tcp/127.0.0.1:{free_port()}",
                                "--port", str(free_port())))
    assert "tls/HOST:PORT only" in line and "--router tcp/127.0.0.1:" in line, line


def test_loopback_is_a_loopback_address_or_localhost():
    from twohr.bus import is_loopback_host
    from twohr_app.access import is_loopback

    for where in ("127.0.0.1", "127.1.2.3", "::1", "[::1]", "localhost", "LocalHost", "tcp/127.0.0.1:7447",
                  "tcp/[::1]:7447", "tcp/localhost:7447#iface=lo"):
        assert is_loopback(where), where
    for where in ("127.attacker.example", "tcp/127.attacker.example:7447", "127.0.0.1.nip.io", "localhost.example",
                  "10.0.0.1", "0.0.0.0", "::", "tcp/0.0.0.0:7447", "example.org", ""):
        assert not is_loopback(where), where
    assert is_loopback_host("127.0.0.1") and not is_loopback_host("127.attacker.example")


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")
def test_keys_add_never_writes_a_key_into_a_file_someone_else_owns(keys, tmp_path):
    theirs = tmp_path / "theirs.bundle"
    theirs.write_text("someone else's")
    os.chown(theirs, 4242, 4242)
    line = one_line_error(twohr("keys", "add", str(keys.folder), "x", "--out", str(theirs)))
    assert "belongs to user 4242" in line and theirs.read_text() == "someone else's", line
    ours = tmp_path / "ours.bundle"
    ours.write_text("old")
    os.chmod(ours, 0o644)
    assert twohr("keys", "add", str(keys.folder), "x", "--out", str(ours)).returncode == 0
    st = ours.stat()
    assert st.st_uid == os.geteuid() and st.st_mode & 0o777 == 0o600 and load_identity(ours).name == "x"
    # a link planted at --out (ours or theirs) is never followed: the file it names keeps its bytes and its owner
    for owner in (os.geteuid(), 4242):
        link = tmp_path / f"link-{owner}.bundle"
        link.symlink_to(theirs)
        os.lchown(link, owner, owner)
        line = one_line_error(twohr("keys", "add", str(keys.folder), f"y{owner}", "--out", str(link)))
        assert "symbolic link" in line, line
        assert link.is_symlink() and theirs.read_text() == "someone else's" and theirs.stat().st_uid == 4242
    # and the one writer of secrets: a file handed out is ours whoever owned the one it replaces
    handed = tmp_path / "handed.bundle"
    handed.write_text("old")
    os.chown(handed, 4242, 4242)
    write_private(handed, "new", keep_owner=False)
    assert handed.stat().st_uid == os.geteuid() and handed.read_text() == "new"
    kept = tmp_path / "kept"
    kept.write_text("old")
    os.chown(kept, 4242, 4242)
    write_private(kept, "new")  # a service's file in its key folder keeps the user the service runs as
    assert kept.stat().st_uid == 4242 and kept.stat().st_mode & 0o777 == 0o600
    link = tmp_path / "kept-link"
    link.symlink_to(kept)
    with pytest.raises(TwohrError, match="symbolic link"):
        write_private(link, "through a link")
    assert kept.read_text() == "new" and link.is_symlink()


def test_add_service_narrows_only_the_folders_it_makes(keys, tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o755)  # a folder others use, as /tmp is
    keys.add_service("detector", "gpu-1", shared)
    assert shared.stat().st_mode & 0o777 == 0o755
    assert {(shared / sub).stat().st_mode & 0o777 for sub in ("services", "services/detector")} == {0o700}
    assert {(shared / "services" / "detector" / name).stat().st_mode & 0o777 for name in ("key.pem", "password")} == {
        0o600}
    made = tmp_path / "made" / "G1"
    keys.add_service("yolo", "gpu-1", made)
    assert made.stat().st_mode & 0o777 == 0o700 and load_identity(made / "services" / "yolo").name == "yolo@gpu-1"
    line = one_line_error(twohr("keys", "add-service", str(keys.folder), "matcher", "gpu-1", "--out",
                                str(tmp_path / "a.bundle"), "--days", "nan"))
    assert "--days nan" in line and "at most 825" in line, line


def test_revoke_says_whether_the_list_is_in_force(keys, tmp_path):
    # no stack: the revocation is saved, and the command says it is not in force yet
    line = one_line_error(twohr("keys", "revoke", str(keys.folder), "c", "--wait", "3"), code=1)
    assert "no stack is running" in line and "in force when the stack starts" in line, line
    assert keys.read().robots["c"].revoked is not None and "c" not in read_users(
        keys.service_folder("router") / "users.txt")
    router = Router(keys, tmp_path / "router.log")
    sessions = []
    try:
        source = join(keys.identity("source"), router.endpoint)
        a, b = join(load_identity(tmp_path / "a.bundle"), router.endpoint), \
            join(load_identity(tmp_path / "b.bundle"), router.endpoint)
        sessions += [source, a, b]
        streams = {name: Stream(source, session, name) for name, session in (("a", a), ("b", b))}
        time.sleep(1.5)
        t0 = time.time()
        done = twohr("keys", "revoke", str(keys.folder), "a")
        assert done.returncode == 0 and "in force" in done.stdout, (done.stdout, done.stderr)
        confirmed = time.time()
        assert confirmed - t0 < 15
        time.sleep(2.0)
        after = time.time()
        time.sleep(2.0)
        assert streams["a"].since(after) == 0 and streams["b"].since(after) > 50, (
            streams["a"].since(after), streams["b"].since(after))

        # a list the router cannot open with (users.txt that Zenoh refuses): it reopens with the old list
        router_folder = keys.service_folder("router")
        listed = json.loads((router_folder / "robots.json").read_text())
        users = (router_folder / "users.txt").read_text()
        write_private(router_folder / "users.txt", users + "not a user line\n")
        write_private(router_folder / "robots.json", json.dumps(listed | {"version": listed["version"] + 1}))
        applied = wait_applied(keys, listed["version"] + 1)
        assert not applied.ok and "invalid format" in applied.error and applied.in_force == listed["version"], applied
        router.wait_for(f"robots' list version {listed['version'] + 1} not applied", 5)
        time.sleep(3.0)  # b reconnects, as every client does after a router restart
        back = time.time()
        time.sleep(2.0)
        assert streams["b"].since(back) > 50 and streams["a"].since(after) == 0
        write_private(router_folder / "users.txt", users)

        # a robot id that `keys add` never makes (fleet.json edited by hand) in the list that revokes b
        fleet = keys.read()
        fleet.robots["x y"] = fleet.robots["b"].model_copy()
        keys._save(fleet)
        line = one_line_error(twohr("keys", "revoke", str(keys.folder), "b"), code=1)
        assert "could not apply" in line and "invalid robot id 'x y'" in line and "goes on with the list" in line
        time.sleep(1.0)
        still = time.time()
        time.sleep(2.0)
        assert streams["b"].since(still) > 50  # not in force: b goes on, and the operator was told
        for stream in streams.values():
            stream.stop()
    finally:
        for session in sessions:
            session.close()
        router.stop()
    line = one_line_error(twohr("keys", "revoke", str(keys.folder), "b", "--wait", "3"), code=1)
    assert "no stack is running" in line  # a router that stopped leaves no lease behind


def wait_applied(fleet: Fleet, version: int, timeout: float = 15.0) -> Applied:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            applied = Applied.model_validate_json((fleet.router_state / APPLIED_FILE).read_bytes())
        except (OSError, ValueError):
            applied = None
        if applied is not None and applied.version >= version:
            return applied
        time.sleep(0.1)
    raise AssertionError(f"no acknowledgement of version {version} within {timeout} s")


CONCURRENT = """
import sys
from pathlib import Path
from twohr_app.fleet import Fleet
fleet, action, names = Fleet(sys.argv[1]), sys.argv[2], sys.argv[3:]
for name in names:
    fleet.add(name, Path(sys.argv[1]).parent / f"{name}.bundle") if action == "add" else fleet.revoke(name)
"""


def test_concurrent_add_and_revoke_lose_nothing(keys, tmp_path):
    old = [f"old{i}" for i in range(10)]
    for name in old:
        keys.add(name, tmp_path / f"{name}.bundle")
    new = [f"new{i}" for i in range(10)]
    procs = [subprocess.Popen([sys.executable, "-c", CONCURRENT, str(keys.folder), "add", *new]),
             subprocess.Popen([sys.executable, "-c", CONCURRENT, str(keys.folder), "revoke", *old])]
    assert [proc.wait(120) for proc in procs] == [0, 0]
    fleet = keys.read()
    assert set(fleet.active()) == {"a", "b", "c", *new}
    assert all(fleet.robots[name].revoked is not None for name in old)
    listed = json.loads((keys.service_folder("router") / "robots.json").read_text())
    assert set(listed["robots"]) == set(fleet.active()) and listed["version"] == fleet.version
    users = read_users(keys.service_folder("router") / "users.txt")
    assert set(new) <= set(users) and not set(old) & set(users)


def test_an_expired_robot_is_cut_mid_session(keys, tmp_path):
    router = Router(keys, tmp_path / "router.log")
    sessions = []
    try:
        # added while the stack runs, with a certificate valid 15 s from now
        bundle, lifetime = tmp_path / "e.bundle", 15.0
        done = twohr("keys", "add", str(keys.folder), "e", "--out", str(bundle), "--days", str(lifetime / 86400))
        assert done.returncode == 0, done.stderr
        expiry = x509.load_pem_x509_certificate(
            load_identity(bundle).cert_pem.encode()).not_valid_after_utc.timestamp()
        assert 0 < expiry - time.time() <= lifetime
        assert wait_applied(keys, keys.read().version).ok
        source = join(keys.identity("source"), router.endpoint)
        e, b = join(load_identity(bundle), router.endpoint), join(load_identity(tmp_path / "b.bundle"),
                                                                   router.endpoint)
        sessions += [source, e, b]
        streams = {name: Stream(source, session, name) for name, session in (("e", e), ("b", b))}
        time.sleep(max(0.0, expiry - time.time()) + 5.0)
        for stream in streams.values():
            stream.stop()
        heard = streams["e"].arrivals
        assert heard and heard[0] < expiry - 2 and expiry - 1 < heard[-1], (expiry, heard[:1], heard[-1:])
        cut = heard[-1] - expiry
        print(f"expired robot's last put arrived {cut:+.3f} s after its certificate's notAfter")
        assert cut < EXPIRY_CUT_S, cut
        assert streams["b"].since(expiry + 1) > 100  # the others go on
        with pytest.raises(IdentityError, match="expired"):  # and it cannot come back with it
            load_identity(bundle)
        # renewed (the CA key is here), it joins again with the same API token, the router not restarted
        token, logged = json.loads(bundle.read_text())["api_token"], len(router.log.read_text())
        done = twohr("keys", "renew", str(keys.folder), "e", "--out", str(bundle), "--days", "1")
        assert done.returncode == 0 and "new certificate until" in done.stdout, done.stderr
        renewed = load_identity(bundle)
        assert renewed.api_token.get_secret_value() == token
        again = join(renewed, router.endpoint)
        sessions.append(again)
        back = Stream(source, again, "e")
        time.sleep(2.0)
        back.stop()
        assert len(back.arrivals) > 50 and "router restarted" not in router.log.read_text()[logged:]
    finally:
        for session in sessions:
            session.close()
        router.stop()
    (keys.folder / "ca.key").rename(tmp_path / "ca.key")
    line = one_line_error(twohr("keys", "renew", str(keys.folder), "e", "--out", str(tmp_path / "e2.bundle")))
    assert "ca.key" in line


def test_the_router_survives_losing_its_users_copy_and_its_watchers_errors_and_retries_a_refused_list(
        keys, tmp_path, caplog):
    """The users file the router runs with is a private copy: a cleaner that removes it (``/tmp`` after ten days)
    costs the next reload nothing; an error in the watcher is logged once and the watching goes on; a list Zenoh
    refuses is tried again (here after 1 s) and applied once it can be, with no new version."""
    from twohr_app.fleet_router import FleetRouter

    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = FleetRouter(keys.service_folder("router"), [endpoint], retry=1.0)
    sessions = []
    try:
        private = router._private
        assert private.parent == keys.router_state and private.stat().st_mode & 0o777 == 0o700
        assert (private / "users.txt").stat().st_mode & 0o777 == 0o600
        shutil.rmtree(private)  # as a cleaner of a temporary folder would
        faults = []
        check = router._check

        def fails_once() -> None:  # an error the watcher did not foresee, once
            if not faults:
                faults.append(time.monotonic())
                raise RuntimeError("a fault in the watcher")
            check()

        router._check = fails_once
        deadline = time.monotonic() + 10
        while not faults:
            assert time.monotonic() < deadline, "the watcher never ran"
            time.sleep(0.1)
        keys.revoke("c")
        applied = wait_applied(keys, keys.read().version)
        assert applied.ok and router.robots == ["a", "b"] and router._private.is_dir() and not private.exists()
        assert "could not check the robots' list (a fault in the watcher); it goes on" in caplog.text
        source = join(keys.identity("source"), endpoint)
        a = join(load_identity(tmp_path / "a.bundle"), endpoint)
        sessions += [source, a]
        stream = Stream(source, a, "a")
        time.sleep(1.5)
        stream.stop()
        assert len(stream.arrivals) > 20  # the router opened after the reload admits a, as before

        # a list Zenoh refuses: acknowledged as not applied, tried again, and in force once the file is fixed
        router_folder = keys.service_folder("router")
        listed = json.loads((router_folder / "robots.json").read_text())
        users = (router_folder / "users.txt").read_text()
        write_private(router_folder / "users.txt", users + "not a user line\n")
        write_private(router_folder / "robots.json", json.dumps(listed | {"version": listed["version"] + 1}))
        refused = wait_applied(keys, listed["version"] + 1)
        assert not refused.ok and "tried again in 1 s" in refused.error, refused
        write_private(router_folder / "users.txt", users)  # fixed, under the same version
        deadline = time.monotonic() + 20
        while router.version != listed["version"] + 1:
            assert time.monotonic() < deadline, "the refused list was not tried again"
            time.sleep(0.1)
        applied = Applied.model_validate_json((keys.router_state / APPLIED_FILE).read_bytes())
        assert applied.ok and applied.version == applied.in_force == listed["version"] + 1, applied
    finally:
        for session in sessions:
            session.close()
        router.close()
    assert not router._private.exists() and not list(keys.router_state.glob("users-*"))


def test_the_denial_log_drains_zenohs_output_when_its_terminal_is_gone_and_remembers_a_bounded_number():
    """Zenoh writes its log from the router's threads into a pipe the denial log reads: that reader must never stop
    (a full pipe would block the router) nor grow without bound, whatever the clients' keys and whether the
    terminal it writes to is still there."""
    from twohr_app.fleet_router import ACL_TARGET, MAX_TRACKED, DenialLog

    read_end, write_end = os.pipe()
    os.close(read_end)
    gone = os.fdopen(write_end, "w")  # a terminal that is gone: every write is a broken pipe
    denials = DenialLog(every=0.05, out=gone)
    zenoh_out, zenoh_in = os.pipe()
    pump = threading.Thread(target=denials._pump, args=(zenoh_out,), daemon=True)
    pump.start()
    record = ("\x1b[2m2026-12-06T15:00:00.000000Z\x1b[0m \x1b[35mTRACE\x1b[0m \x1b[2mrx-1\x1b[0m "
              f"\x1b[2m{ACL_TARGET}\x1b[0m\x1b[2m:\x1b[0m ")
    lines = ["\x1b[2m2026-12-06T15:00:00.000000Z\x1b[0m  INFO zenoh::net::runtime: a line to pass through\n"]
    extra = 500
    lines += [f"{record}{i:x} on Interface(lo)+CertCommonName(b)+Username(b)+Transport(Tls)+{i:x} is unauthorized "
              f"to Put (ingress) on twohr/b/k{i}\n" for i in range(MAX_TRACKED + extra)]
    text = "".join(lines).encode()
    assert len(text) > 1 << 20  # far more than a pipe holds: the writer blocks unless it is read

    def write() -> None:
        with os.fdopen(zenoh_in, "wb") as pipe:
            pipe.write(text)

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    writer.join(120)
    pump.join(120)
    assert not writer.is_alive() and not pump.is_alive(), "the denial log stopped reading"
    assert denials.skipped == 0 and len(denials.counts) == MAX_TRACKED
    assert ("b", "put", f"twohr/b/k{MAX_TRACKED + extra - 1}") in denials.counts
    assert ("b", "put", "twohr/b/k0") not in denials.counts  # the oldest are forgotten
    assert len(denials._filter._names) == MAX_TRACKED
    with contextlib.suppress(OSError):
        gone.close()


def test_a_robot_reads_the_others_poses_but_only_its_own_map_points(keys, tmp_path):
    """On the keyed router: the tracker publishes a's and b's poses and live map points (``landmarks``); robot b
    hears a's poses and its own points, and none of a's points (another robot's map is not its to read)."""
    router = Router(keys, tmp_path / "router.log")
    sessions = []
    try:
        tracker = join(keys.identity("tracker"), router.endpoint)
        b = join(load_identity(tmp_path / "b.bundle"), router.endpoint)
        sessions += [tracker, b]
        heard: dict[str, int] = {}

        def count(sample) -> None:
            heard[str(sample.key_expr)] = heard.get(str(sample.key_expr), 0) + 1

        for key in ("twohr/a/pose", "twohr/a/landmarks", "twohr/b/landmarks"):
            b.declare_subscriber(key, count)
        time.sleep(1.0)  # the subscriptions reach the router
        for _ in range(20):
            for key in ("twohr/a/pose", "twohr/a/landmarks", "twohr/b/landmarks"):
                tracker.put(key, b"x")
            time.sleep(0.02)
        time.sleep(1.0)
        assert heard.get("twohr/a/pose") == 20 and heard.get("twohr/b/landmarks") == 20, heard
        assert "twohr/a/landmarks" not in heard, heard
    finally:
        for session in sessions:
            session.close()
        router.stop()


def test_giving_the_key_folders_away_never_follows_a_link_planted_in_one(keys, tmp_path):
    """``twohr keys init --owner``: a link in a service's folder is given away itself, not the file it points to."""
    if os.geteuid() != 0:
        pytest.skip("giving files to another user needs root")
    target = tmp_path / "elsewhere.txt"
    target.write_text("not the fleet's")
    planted = keys.service_folder("detector") / "planted"
    planted.symlink_to(target)
    keys.give({"*": 54321})
    assert target.stat().st_uid == 0 and planted.lstat().st_uid == 54321
    assert keys.service_folder("detector").stat().st_uid == 54321
