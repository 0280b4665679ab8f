"""The stack's router on a fleet's bus: mutual TLS with the fleet's CA, one identity per robot, revocation while
the fleet runs, and a log of what it denies.

Zenoh 1.x reads its users and its access-control list once, when the router starts, and has no certificate
revocation list. So :class:`FleetRouter` watches the robots' list in its key folder (``robots.json``, which
``twohr keys revoke`` rewrites) and, when it changes, closes the router and opens it again with the new users
file and access list: a revoked robot's password is gone from the users file, so the router refuses its
connection at the handshake (Zenoh's ``usrpwd`` authentication, inside TLS), and its certificate's common name
is gone from the access list. Every other client, the services included, reconnects by itself (Zenoh's client
retry, about 1 s) and declares its subscriptions again; their sessions go on.

Zenoh logs a denial only at TRACE level (``zenoh::net::routing::interceptor::access_control``), one line per
denied message, on standard output. :class:`DenialLog` turns that on for this target alone and reads this
process's standard output through a pipe: it prints the first denial of each (identity, action, key) as one line
and a count of the rest every ``every`` seconds, and passes every other line through.
"""

from __future__ import annotations

import logging
import os
import re
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from twohr.bus import RouterSecurity, start_router
from twohr.identity import load_identity

from .access import access_control
from .fleet import USERS_FILE, active_robots

log = logging.getLogger("twohr.router")

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_DENIAL = re.compile(r"is unauthorized to (?P<action>\w+) \((?P<flow>\w+)\) on (?P<key>\S+)")
_NAME = re.compile(r"(CertCommonName|Username)\(([^)]*)\)")
_CACHING = re.compile(r"ThreadId\((\d+)\).*caching permissions for `([^`]*)`")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_SUBJECT = re.compile(r"([0-9a-f]+) on Interface\(")
_CACHED = re.compile(r"Using cached result: ([0-9a-f]+) is")


class DenialFilter:
    """Tells real denials from Zenoh's permission caching: when a client declares a key, Zenoh checks every kind
    of message on it at once and logs each refusal, right after a "caching permissions for `KEY`" line on the same
    thread. Those are not denials of anything sent; a denial of a message sent stands alone."""

    def __init__(self) -> None:
        self._caching: dict[str, str] = {}  # thread -> the key whose permissions it is caching
        self._names: dict[str, str] = {}  # Zenoh id -> identity, for denials Zenoh logs by id alone (cached ones)

    def denial(self, line: str) -> tuple[str, str, str] | None:
        """``(identity, action, key)`` of a denied message in this log line, None for any other line."""
        line = _ANSI.sub("", line)
        subject, names = _SUBJECT.search(line), dict(_NAME.findall(line))
        if subject is not None and names:
            self._names[subject[1]] = names.get("CertCommonName") or names["Username"]
        caching = _CACHING.search(line)
        if caching is not None:
            self._caching[caching[1]] = caching[2]
            return None
        thread = _THREAD.search(line)
        if thread is not None and thread[1] in self._caching:
            if line.rstrip().endswith(f" on {self._caching[thread[1]]}"):
                return None  # the block goes on: allowed and refused kinds of message on the same key
            del self._caching[thread[1]]
        denial = parse_denial(line)
        cached = _CACHED.search(line)
        if denial is not None and denial[0] == "unknown" and cached is not None:
            denial = (self._names.get(cached[1], cached[1]), *denial[1:])
        return denial


def parse_denial(line: str) -> tuple[str, str, str] | None:
    """``(identity, action, key)`` of a Zenoh ACL denial line, None for any other line."""
    line = _ANSI.sub("", line)
    match = _DENIAL.search(line)
    if match is None or match["flow"] != "ingress":  # an egress denial mirrors an ingress one, or is routine
        return None
    names = dict(_NAME.findall(line))
    who = names.get("CertCommonName") or names.get("Username") or "unknown"
    return who, match["action"].lower(), match["key"]


class DenialLog:
    """Reads this process's standard output (file descriptor 1, where Zenoh logs) through a pipe: Zenoh's ACL trace
    lines become one line per denied (identity, action, key), everything else passes through unchanged."""

    def __init__(self, every: float = 10.0, out=None) -> None:
        self.every = every
        self.counts: Counter[tuple[str, str, str]] = Counter()
        self._reported: Counter[tuple[str, str, str]] = Counter()
        self._out = out
        self._filter = DenialFilter()
        self._thread: threading.Thread | None = None

    def start(self) -> DenialLog:
        import zenoh

        sys.stdout.flush()
        original = os.dup(1)
        read, write = os.pipe()
        os.dup2(write, 1)
        os.close(write)
        self._out = self._out or os.fdopen(original, "w", buffering=1)
        sys.stdout = os.fdopen(os.dup(1), "w", buffering=1)  # Python's own prints go the same way, in order
        zenoh.init_log_from_env_or(f"error,{ACL_TARGET}=trace")
        self._thread = threading.Thread(target=self._pump, args=(read,), name="denial-log", daemon=True)
        self._thread.start()
        return self

    def _pump(self, fd: int) -> None:
        last = time.monotonic()
        with os.fdopen(fd, "r", errors="replace") as lines:
            for line in lines:
                denial = self._filter.denial(line) if ACL_TARGET in line else None
                if denial is not None:
                    self.counts[denial] += 1
                    if self.counts[denial] == 1:
                        self._say(f"twohr router: denied {denial[0]!r} {denial[1]} on {denial[2]}")
                        self._reported[denial] = 1
                elif ACL_TARGET not in line:
                    self._out.write(line)
                    self._out.flush()
                if time.monotonic() - last >= self.every:
                    last = time.monotonic()
                    self._summarise()

    def _summarise(self) -> None:
        for denial, count in self.counts.items():
            if count > self._reported[denial]:
                self._say(f"twohr router: denied {denial[0]!r} {denial[1]} on {denial[2]} {count} times so far")
                self._reported[denial] = count

    def _say(self, text: str) -> None:
        self._out.write(text + "\n")
        self._out.flush()


class FleetRouter:
    """The stack's router of a fleet, run from its key folder (``<keys>/services/router``): listens on ``tls/``
    endpoints only, admits the services and the robots not revoked, each by its certificate and password, and
    restarts with the new list when ``robots.json`` changes (checked every ``poll`` s)."""

    def __init__(self, folder: str | Path, listen: list[str], ros2_domain: int = 0, poll: float = 0.5) -> None:
        self.folder = Path(folder)
        self.listen = listen
        self.ros2_domain = ros2_domain
        self.poll = poll
        self.identity = load_identity(self.folder)
        self.version, self.robots = active_robots(self.folder)
        self.restarts = 0
        self.session = self._open()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="fleet-watch", daemon=True)
        self._watcher.start()

    def _open(self):
        security = RouterSecurity(users_file=self.folder / USERS_FILE, identity=self.identity,
                                  access_control=access_control(self.ros2_domain, robots=self.robots))
        return start_router(self.listen, security)

    def _watch(self) -> None:
        while not self._stop.wait(self.poll):
            try:
                version, robots = active_robots(self.folder)
            except (OSError, ValueError):  # being rewritten: read it again next time
                continue
            if version != self.version:
                self.reload(version, robots)

    def reload(self, version: int, robots: list[str]) -> None:
        """Close the router and open it again with the robots' new list."""
        with self._lock:
            gone = sorted(set(self.robots) - set(robots))
            t0 = time.monotonic()
            self.session.close()
            self.version, self.robots = version, robots
            self.session = self._open()
            self.restarts += 1
        log.warning("robots' list version %d: %s; router restarted in %.2f s", version,
                    f"revoked {', '.join(gone)}" if gone else f"{len(robots)} robots", time.monotonic() - t0)

    @property
    def info(self):
        """The current router session's ``info`` (its Zenoh id)."""
        return self.session.info

    def close(self) -> None:
        self._stop.set()
        self._watcher.join(timeout=5)
        with self._lock:
            self.session.close()
