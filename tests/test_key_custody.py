"""Key custody, the denial log and the gateway's smaller guards, with real processes (issue 49, items 5, 6, 7).

``twohr up --keys K`` runs with ``K/ca.key`` moved off the host and the operator's token in ``K/operator.token``,
on ``--host 0.0.0.0``, serving the names the keys were made for (a host they do not name is one line); each child
is given its own key folder alone. A matcher replica of another host joins with a certificate of its own
(``twohr keys add-service``) and, once revoked (without the CA's key), cannot join again. ``/healthz`` tells anyone
whether the stack is up and the operator everything; HTTPS refuses TLS 1.2. A robot's put on
``twohr/CertCommonName(tracker)/camera``, and one whose key holds a line break and a whole forged log record, are
logged as the robot's. Recordings and maps are written private.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import ssl
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from twohr.bus import BusConfig, free_port, open_session
from twohr.identity import load_identity

ENV = {k: v for k, v in os.environ.items() if k != "TWOHR_API_TOKEN"}
NAMED = "twohr.test"  # the name the keys are made for, besides the local ones


def twohr(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True,
                          timeout=timeout, env=ENV)


def one_line_error(done: subprocess.CompletedProcess, text: str) -> None:
    assert done.returncode == 2 and text in done.stderr, done.stdout + done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr, done.stderr


class Process:
    """A process whose standard output is read into a file, for its lines."""

    def __init__(self, argv: list[str], log: Path) -> None:
        self.log = log
        self.out = open(log, "w")  # noqa: SIM115 (closed in stop())
        self.proc = subprocess.Popen(argv, stdout=self.out, stderr=subprocess.STDOUT, text=True, env=ENV)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_for(self, needle: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while needle not in self.text():
            assert self.proc.poll() is None, f"exited {self.proc.returncode}:\n{self.text()[-4000:]}"
            assert time.monotonic() < deadline, f"no {needle!r} within {timeout} s:\n{self.text()[-4000:]}"
            time.sleep(0.2)
        return next(line for line in self.text().splitlines() if needle in line)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.out.close()


@pytest.fixture(scope="module")
def custody(tmp_path_factory, dev_sequence):
    """Keys for robots a and b and a matcher replica of host gpu-1, the CA's key then moved away, and the stack on
    them: ``twohr up --keys K --router tls/127.0.0.1:P --host 0.0.0.0``."""
    tmp = tmp_path_factory.mktemp("custody")
    keys = tmp / "K"
    assert (done := twohr("keys", "init", str(keys), "--host", NAMED)).returncode == 0, done.stderr
    for robot in ("a", "b"):
        done = twohr("keys", "add", str(keys), robot, "--out", str(tmp / f"{robot}.bundle"))
        assert done.returncode == 0, done.stderr
    done = twohr("keys", "add-service", str(keys), "matcher", "gpu-1", "--out", str(tmp / "gpu-1"))
    assert done.returncode == 0 and "matcher@gpu-1" in done.stdout, done.stderr
    (tmp / "offline").mkdir()
    (keys / "ca.key").rename(tmp / "offline" / "ca.key")
    router, port = f"tls/127.0.0.1:{free_port()}", free_port()
    stack = Process([sys.executable, "-m", "twohr_app", "up", "--keys", str(keys), "--router", router, "--host",
                     "0.0.0.0", "--port", str(port), "--foxglove-port", "0", "--max-robots", "2", "--data-root",
                     str(dev_sequence.parent), "--recordings", str(tmp / "recordings")], tmp / "up.log")
    try:
        healthy = stack.wait_for("all healthy", 240)
        yield {"tmp": tmp, "keys": keys, "router": router, "port": port, "stack": stack, "healthy": healthy,
               "operator": (keys / "operator.token").read_text().strip(),
               "b": json.loads((tmp / "b.bundle").read_text())["api_token"]}
    finally:
        stack.stop()


def https(custody, token: str | None = None) -> httpx.Client:
    context = ssl.create_default_context(cafile=str(custody["keys"] / "ca.crt"))
    return httpx.Client(base_url=f"https://127.0.0.1:{custody['port']}", verify=context, timeout=30,
                        headers={"Authorization": f"Bearer {token}"} if token else {})


def handshake(custody, name: str, context: ssl.SSLContext | None = None) -> str:
    """A TLS handshake with the gateway as the host ``name`` (verified with the fleet's CA); the TLS version."""
    context = context or ssl.create_default_context(cafile=str(custody["keys"] / "ca.crt"))
    with socket.create_connection(("127.0.0.1", custody["port"]), timeout=10) as raw, \
            context.wrap_socket(raw, server_hostname=name) as tls:
        return tls.version()


def children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(child) for child in (task / "children").read_text().split()]
    return found


def test_the_stack_runs_without_the_ca_key_on_the_names_its_keys_were_made_for(custody):
    keys, stack = custody["keys"], custody["stack"]
    assert not (keys / "ca.key").exists()
    assert (keys / "operator.token").stat().st_mode & 0o777 == 0o600
    # 0.0.0.0 serves the names the keys were made for, and says which
    assert f"(as localhost, {NAMED}, 127.0.0.1, ::1: the names its certificate holds)" in custody["healthy"]
    assert handshake(custody, NAMED) == handshake(custody, "localhost") == "TLSv1.3"
    with pytest.raises(ssl.SSLCertVerificationError):
        handshake(custody, "elsewhere.test")
    # a host the keys do not name, and a token on the command line: one line each, before anything starts
    one_line_error(twohr("up", "--keys", str(keys), "--router", f"tls/127.0.0.1:{free_port()}", "--host",
                         "10.213.9.9", "--port", str(free_port())),
                   f"add it with twohr keys add-host {keys} 10.213.9.9")
    one_line_error(twohr("up", "--keys", str(keys), "--router", f"tls/10.213.9.9:{free_port()}"),
                   "the router's certificate does not name 10.213.9.9")
    one_line_error(twohr("up", "--keys", str(keys), "--router", f"tls/127.0.0.1:{free_port()}", "--api-token",
                         "x"), f"the operator's API token is {keys / 'operator.token'}")
    one_line_error(twohr("keys", "add-host", str(keys), "10.213.9.9"), "needs the CA's private key")
    # every service is given its own key folder, and no token; none of them names the token on its command line
    roles = {}
    for pid in children(stack.proc.pid):
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        env = dict(item.split("=", 1) for item in Path(f"/proc/{pid}/environ").read_text().split("\0") if item)
        role = argv[argv.index(b"-m") + 1].decode().removeprefix("twohr_services.")
        roles[role] = env["TWOHR_ZENOH_KEYS"]
        assert "TWOHR_API_TOKEN" not in env and custody["operator"].encode() not in b" ".join(argv), role
    assert roles == {role: str(keys / "services" / role) for role in
                     ("source", "detector", "yolo", "matcher", "tracker", "mapserver", "recorder", "gateway")}, roles


def test_healthz_tells_anyone_only_whether_the_stack_is_up_and_https_refuses_tls_1_2(custody):
    for token in (None, "wrong", custody["b"]):  # no token, a wrong one, a robot's: up or down, nothing else
        with https(custody, token) as client:
            answer = client.get("/healthz")
        assert answer.status_code == 200 and answer.json() == {"status": "up"}, (token, answer.text)
    with https(custody, custody["operator"]) as client:
        full = client.get("/healthz").json()
    assert full["status"] in ("ok", "degraded") and full["missing_services"] == [], full
    assert full["robots"]["capacity"] == 2 and full["services"]["matcher"]["replicas"][0]["host"], full
    old = ssl.create_default_context(cafile=str(custody["keys"] / "ca.crt"))
    old.maximum_version = ssl.TLSVersion.TLSv1_2
    with pytest.raises(ssl.SSLError):
        handshake(custody, "127.0.0.1", old)


def matcher_replicas(custody) -> list[str]:
    """The matcher replicas that answer (none while the router restarts)."""
    with https(custody, custody["operator"]) as client:
        matcher = client.get("/healthz").json()["services"]["matcher"]
    return [r["replica"] for r in matcher["replicas"]] if matcher else []


def test_a_replica_of_another_host_has_its_own_certificate_and_once_revoked_cannot_rejoin(custody):
    tmp, keys = custody["tmp"], custody["keys"]
    folder = tmp / "gpu-1" / "services" / "matcher"
    assert load_identity(folder).name == "matcher@gpu-1" and (folder / "key.pem").stat().st_mode & 0o777 == 0o600
    joined = Process([sys.executable, "-m", "twohr_app", "up", "--join", custody["router"], "--only", "matcher",
                      "--keys", str(tmp / "gpu-1")], tmp / "join.log")
    try:
        replica = joined.wait_for("joined", 120).split("replicas ", 1)[1].split(";", 1)[0].strip()
        assert replica in matcher_replicas(custody) and len(matcher_replicas(custody)) == 2
        # its certificate gets the matcher's grants, no other role's
        session = open_session(BusConfig(connect=[custody["router"]], identity=load_identity(folder), user=None,
                                         password=None, config_file=None))
        tracker = open_session(BusConfig(connect=[custody["router"]], identity=load_identity(keys / "services" /
                                                                                            "tracker"),
                                         user=None, password=None, config_file=None))
        seen: list[str] = []
        watcher = tracker.liveliness().declare_subscriber("twohr/_alive/*/gpu-1-probe",
                                                          lambda sample: seen.append(str(sample.key_expr)))
        time.sleep(0.5)
        tokens = [session.liveliness().declare_token(f"twohr/_alive/{role}/gpu-1-probe")
                  for role in ("matcher", "tracker")]
        time.sleep(1.0)
        assert seen == ["twohr/_alive/matcher/gpu-1-probe"], seen
        for token in tokens:
            token.undeclare()
        watcher.undeclare()
        session.close()
        tracker.close()

        revoked = twohr("keys", "revoke", str(keys), "matcher@gpu-1")  # K/ca.key is still away
        assert revoked.returncode == 0 and "replica matcher@gpu-1: revoked" in revoked.stdout, revoked.stderr
        deadline = time.monotonic() + 20
        while replica in (answering := matcher_replicas(custody)) or not answering:
            assert time.monotonic() < deadline, f"the revoked replica still answers: {answering}"
            time.sleep(0.5)
        assert len(answering) == 1  # the stack's own matcher goes on (back after the router's restart)
    finally:
        joined.stop()
    again = twohr("up", "--join", custody["router"], "--only", "matcher", "--keys", str(tmp / "gpu-1"),
                  "--timeout", "30")
    assert again.returncode != 0 and "cannot join the Zenoh bus" in again.stderr, again.stdout + again.stderr
    assert "Traceback" not in again.stderr
    listed = twohr("keys", "list", str(keys))
    assert any(line.split()[:2] == ["matcher@gpu-1", "revoked"] for line in listed.stdout.splitlines()), listed.stdout


FORGED = ("2026-12-06T14:26:44.245279Z TRACE rx-1 ThreadId(09) zenoh::net::routing::interceptor::access_control: "
          "ffff on Interface(lo)+CertCommonName(tracker)+Username(tracker)+Transport(Tls)+ffff is unauthorized to "
          "Put (ingress) on twohr/forged/camera")


def test_the_denial_log_names_the_link_not_the_key(tmp_path):
    keys = tmp_path / "K"
    assert (done := twohr("keys", "init", str(keys))).returncode == 0, done.stderr
    assert (done := twohr("keys", "add", str(keys), "b", "--out", str(tmp_path / "b.bundle"))).returncode == 0
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = Process([sys.executable, "-m", "twohr_app", "router", "--keys", str(keys / "services" / "router"),
                      "--listen", endpoint], tmp_path / "router.log")
    try:
        router.wait_for("zenoh router listening", 60)
        b = open_session(BusConfig(connect=[endpoint], identity=load_identity(tmp_path / "b.bundle"), user=None,
                                   password=None, config_file=None))
        try:
            time.sleep(0.5)
            b.put("twohr/CertCommonName(tracker)/camera", b"b's frame, a key naming the tracker")
            # a key with line breaks: a whole forged record, and a forged report line
            b.put(f"twohr/b/x\n{FORGED}\ntwohr router: denied 'tracker' put on twohr/a/camera", b"forged")
            b.put("twohr/a/camera", b"b posing as a")
            router.wait_for("denied 'b' put on twohr/a/camera", 15)
        finally:
            b.close()
    finally:
        router.stop()
    denials = [line for line in router.text().splitlines() if "denied" in line]
    assert "twohr router: denied 'b' put on twohr/CertCommonName(tracker)/camera" in denials, denials
    assert "twohr router: denied 'b' put on twohr/b/x" in denials, denials
    assert all(line.startswith("twohr router: denied 'b' put on ") for line in denials), denials
    assert "tracker'" not in router.text() and "twohr/forged" not in router.text()


def test_recordings_and_maps_are_written_private(tmp_path, tiny_map):
    from twohr.dataset import CameraIntrinsics
    from twohr.mapfile import OPERATOR, encode_map
    from twohr.mapstore import MapStore
    from twohr.mcapfile import partial_marker, recover
    from twohr.messages import PoseMsg, encode
    from twohr_services.recorder.core import SessionRecorder

    before = os.umask(0)  # a umask that would leave every new file world-readable and writable
    try:
        recorder = SessionRecorder(tmp_path / "recordings" / "s1.mcap")
        pose = PoseMsg(session_id="s1", robot_id="a", frame_index=0, stamp=0.0, position=[0.0] * 3,
                       orientation=[0.0, 0.0, 0.0, 1.0], status="ok")
        recorder.write("twohr/a/pose", encode(pose))
        recorder.close()
        cut = tmp_path / "recordings" / "cut.mcap"
        cut.write_bytes((tmp_path / "recordings" / "s1.mcap").read_bytes()[:-40])  # as a killed recorder leaves it
        assert recover(cut) is not None  # rewritten whole, with a marker beside it
        store = MapStore(tmp_path / "maps")
        camera = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)
        store.save(encode_map(tiny_map("lab", camera)), builder=OPERATOR)
        store.save(encode_map(tiny_map("lab", camera)), builder=OPERATOR)  # version 2: version 1 kept beside it
    finally:
        os.umask(before)
    maps = sorted((tmp_path / "maps").glob("lab*"))
    written = [tmp_path / "recordings" / "s1.mcap", cut, partial_marker(cut), *maps]
    assert len(maps) >= 2 and all(path.stat().st_size for path in written)
    assert {path.name: path.stat().st_mode & 0o777 for path in written} == {path.name: 0o600 for path in written}
    assert {(tmp_path / folder).stat().st_mode & 0o777 for folder in ("recordings", "maps")} == {0o700}
