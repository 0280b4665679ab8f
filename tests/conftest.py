"""Test hosts made of Linux network namespaces, for the tests that run the stack across hosts
(test_across_hosts.py, test_fleet_hosts.py). Addresses exist only inside the namespaces a test makes; every
namespace and every process started in one is removed when the test's network closes.

Also one ``twohr run --view`` on real frames, whose stream test_run_view.py reads and whose report
test_run_report.py reads (:func:`viewed_run`)."""

from __future__ import annotations

import ctypes
import os
import secrets
import shutil
import signal
import subprocess
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CLONE_NEWNET = 0x40000000


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        raise OSError(ctypes.get_errno(), "setns failed")


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


class Program:
    """A process started on a host, its output in a log file (a pipe nobody reads would stall it)."""

    def __init__(self, argv: list[str], env: dict[str, str], log: Path) -> None:
        self.log = log
        with open(log, "w") as out:
            # its own process group, so that what it started goes with it
            self.proc = subprocess.Popen(argv, env=env, text=True, stdout=out, stderr=subprocess.STDOUT, cwd=REPO,
                                         start_new_session=True)

    def output(self) -> str:
        return self.log.read_text()

    def first_line(self, timeout: float) -> str:
        """The first line it prints; fails if it exits or stays silent for ``timeout`` seconds."""
        return self.wait_for(lambda text: "\n" in text, timeout).splitlines()[0]

    def wait_for(self, done, timeout: float) -> str:
        """Its output once ``done(output)`` holds; fails if it exits first or ``timeout`` seconds pass."""
        deadline = time.monotonic() + timeout
        while not done(text := self.output()):
            assert self.proc.poll() is None, f"{self.proc.args} exited with {self.proc.returncode}: {text[-3000:]}"
            assert time.monotonic() < deadline, f"not there within {timeout} s from {self.proc.args}: {text[-2000:]}"
            time.sleep(0.05)
        return text

    def wait(self, timeout: float) -> int:
        return self.proc.wait(timeout)

    def stop(self, grace: float = 15.0) -> str:
        """SIGTERM, then SIGKILL to its whole process group after ``grace``; returns what it printed."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)  # anything it left behind
        except ProcessLookupError:
            pass
        self.proc.wait()
        return self.output()


class Network:
    """Hosts as network namespaces, linked by veth pairs, and the processes started in them; :meth:`close`
    removes all of it."""

    def __init__(self, tmp: Path, hosts: list[str]) -> None:
        self.tmp = tmp
        self.tag = secrets.token_hex(3)
        self.ns = {host: f"twohr-{self.tag}-{host}" for host in hosts}
        self.devices: dict[tuple[str, str], str] = {}  # (host, peer) -> the host's end of their link
        self.programs: list[Program] = []
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("TWOHR_ZENOH_")} | {
            "PYTHONUNBUFFERED": "1", "TWOHR_LOG_LEVEL": "WARNING"}

    def make(self, links: list[tuple[str, str, str, str]]) -> None:
        """Make the namespaces and one /30 link per ``(host a, address a, host b, address b)``."""
        for name in self.ns.values():
            _ip("netns", "add", name)
        for name in self.ns.values():
            _ip("-n", name, "link", "set", "lo", "up")
        for i, (a, addr_a, b, addr_b) in enumerate(links):
            self._link(a, addr_a, b, addr_b, f"th{self.tag}{i}")

    def _link(self, a: str, addr_a: str, b: str, addr_b: str, name: str) -> None:
        # made inside namespace a with its peer moved straight into b: nothing appears in the host's own namespace
        _ip("-n", self.ns[a], "link", "add", f"{name}a", "type", "veth", "peer", "name", f"{name}b",
            "netns", self.ns[b])
        for host, dev, addr in ((a, f"{name}a", addr_a), (b, f"{name}b", addr_b)):
            _ip("-n", self.ns[host], "addr", "add", f"{addr}/30", "dev", dev)
            _ip("-n", self.ns[host], "link", "set", dev, "up")
        self.devices[(a, b)], self.devices[(b, a)] = f"{name}a", f"{name}b"

    def start(self, host: str, *argv: str, env: dict[str, str] | None = None) -> Program:
        program = Program(["ip", "netns", "exec", self.ns[host], *argv], env or self.env,
                          self.tmp / f"{host}-{len(self.programs)}.log")
        self.programs.append(program)
        return program

    def run(self, host: str, *argv: str, env: dict[str, str] | None = None,
            timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", "netns", "exec", self.ns[host], *argv], env=env or self.env, text=True,
                              capture_output=True, timeout=timeout, cwd=REPO)

    @contextmanager
    def inside(self, host: str):
        """Run this thread's sockets on ``host`` (an HTTP client talking to a gateway there)."""
        with open("/proc/thread-self/ns/net") as home, open(f"/run/netns/{self.ns[host]}") as there:
            _setns(there.fileno())
            try:
                yield
            finally:
                _setns(home.fileno())

    def close(self) -> None:
        for program in reversed(self.programs):
            program.stop()
        for name in self.ns.values():
            subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)


def netns_unavailable() -> str | None:
    """Why network namespaces cannot be made here, or None."""
    if shutil.which("ip") is None:
        return "the iproute2 `ip` command is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root (CI runs as root)"
    probe = f"twohr-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"`ip netns add` is not permitted here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


@pytest.fixture(scope="session")
def network():
    """``network(tmp, hosts)``: a :class:`Network` of those hosts (skips where namespaces cannot be made)."""
    reason = netns_unavailable()
    if reason:
        pytest.skip(f"cannot make network namespaces: {reason}")
    return Network


@pytest.fixture(scope="session")
def self_signed_bundle():
    """``self_signed_bundle(name, path)``: write a robot bundle for ``name`` whose certificate is its own CA (an
    intruder's: right name, no fleet behind it); returns the path."""
    import datetime
    import json

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    from pydantic import SecretStr

    from twohr.identity import Bundle
    from twohr_app.fleet import pem, reveal

    def make(name: str, path: Path) -> Path:
        key = ec.generate_private_key(ec.SECP256R1())
        subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
        now = datetime.datetime.now(datetime.timezone.utc)
        cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
                .serial_number(1).not_valid_before(now - datetime.timedelta(hours=1))
                .not_valid_after(now + datetime.timedelta(days=1)).sign(key, hashes.SHA256()))
        bundle = Bundle(name=name, ca_pem=pem(cert), cert_pem=pem(cert), key_pem=SecretStr(pem(key)),
                        password=SecretStr("guess"))
        path.write_text(json.dumps(reveal(bundle)))
        return path

    return make


VIEWED_FRAMES = 90


@pytest.fixture(scope="session")
def viewed_run(dev_sequence, tmp_path_factory):
    """``twohr run --view`` on the first :data:`VIEWED_FRAMES` dev frames with the default settings, a Foxglove
    client subscribed from its first line on, before the models load (no frame is missed): a dict of the run's
    ``out`` folder, its ``first_line``, ``stdout`` (after that line), ``stderr``, ``returncode`` and the
    ``client``, and its ``frames``. The run writes everything ``twohr run`` writes, so the report's test reads the
    same run."""
    import sys

    from twohr.bus import free_port
    from twohr.foxglove_live import FoxgloveClient

    out, port = tmp_path_factory.mktemp("viewed_run") / "run", free_port()
    proc = subprocess.Popen([sys.executable, "-m", "twohr_app", "run", "--sequence", str(dev_sequence), "--out",
                             str(out), "--frames", str(VIEWED_FRAMES), "--quiet", "--view", "--view-port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = None
    try:
        first_line = proc.stdout.readline()
        if first_line.startswith("live view: "):
            client = FoxgloveClient(f"ws://127.0.0.1:{port}")
        stdout, stderr = proc.communicate(timeout=600)
    finally:
        proc.kill()
    time.sleep(0.2)
    yield {"out": out, "frames": VIEWED_FRAMES, "port": port, "first_line": first_line, "stdout": stdout,
           "stderr": stderr, "returncode": proc.returncode, "client": client}
    if client is not None:
        client.close()
