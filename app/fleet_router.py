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
denied message, on standard output. :class:`DenialLog` turns that on for this target alone and reads what Zenoh
writes to this process's standard output through a pipe: it prints the first denial of each (identity, action,
key) as one line and a count of the rest every ``every`` seconds, and passes every other line through.

The identity in a denial comes from the link, never from text a client chose: only the part of Zenoh's line
before "is unauthorized" (the link's interface, certificate common name and user name, which the router's TLS
and password checks established) is read for it, and the key, which the client chose, is read as a key and
nothing else. A key may hold a line break; the lines after it are not Zenoh's, and a real record is told from
them by its first bytes (the timestamp in ANSI escapes, which Zenoh writes escaped in any text from a client).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import re
import shutil
import socket
import sys
import tempfile
import threading
import time
from collections import OrderedDict
from pathlib import Path

from pydantic import BaseModel, Field, SecretStr

from twohr.bus import RouterSecurity, start_router
from twohr.errors import TwohrError
from twohr.identity import load_identity
from twohr.keys import ROBOT_PATTERN

from .access import access_control
from .fleet import USERS_FILE, Fleet, FleetError, private_folder, write_private
from .fleet.store import ROBOTS_FILE

log = logging.getLogger("twohr.router")

#: in the router's state folder: its lease (touched while it runs) and its acknowledgement of the last list
LEASE_FILE, APPLIED_FILE = "router.lease", "applied.json"
#: a lease older than this (s) is a router's that is gone; how long ``keys revoke`` waits for the acknowledgement
LEASE_STALE, CONFIRM_TIMEOUT = 5.0, 15.0
#: a list the router could not open with is tried again after this (s), doubling up to the second figure: each try
#: restarts the router, which every client feels for about a second
RETRY_FIRST, RETRY_MAX = 10.0, 300.0
#: the most (identity, action, key) triples and Zenoh ids the denial log remembers: a client chooses its keys
MAX_TRACKED = 10_000

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_UNAUTHORIZED = " is unauthorized to "
_DENIAL = re.compile(r"(?P<action>\w+) \((?P<flow>\w+)\) on (?P<key>.*)\Z", re.S)
_NAME = re.compile(r"(CertCommonName|Username)\(([^)]*)\)")
_CACHING = re.compile(r"ACL \(\w+\): caching permissions for `(.*)` \.\.\.\Z", re.S)
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_SUBJECT = re.compile(r"([0-9a-f]+) on Interface\(")
_CACHED = re.compile(r"Using cached result: ([0-9a-f]+)\Z")
#: the first bytes of a record Zenoh writes: its timestamp, dimmed with raw escape bytes (a client's text has none)
_RECORD = re.compile(r"\x1b\[2m\d{4}-\d\d-\d\dT")
_ACL_RECORD = f"\x1b[2m{ACL_TARGET}\x1b[0m"


def _message(line: str) -> tuple[str | None, str] | None:
    """``(thread, message)`` of a line of Zenoh's ACL target (ANSI codes gone), None for any other line: the first
    ``<target>: `` ends Zenoh's own header."""
    head, target, message = _ANSI.sub("", line).rstrip("\r\n").partition(f"{ACL_TARGET}: ")
    if not target:
        return None
    thread = _THREAD.search(head)
    return (thread[1] if thread else None), message


def _identity(subject: str) -> str | None:
    """The certificate common name (else the user name) in the subject part of a line, the part before "is
    unauthorized": what the link authenticated."""
    names = dict(_NAME.findall(subject))
    return names.get("CertCommonName") or names.get("Username")


class Bounded(OrderedDict):
    """A dict that keeps its ``limit`` most recently set keys (:meth:`put`) and forgets the oldest."""

    def __init__(self, limit: int = MAX_TRACKED) -> None:
        super().__init__()
        self.limit = limit

    def put(self, key, value) -> None:
        self[key] = value
        self.move_to_end(key)
        while len(self) > self.limit:
            self.popitem(last=False)


def printable(text: str) -> str:
    """``text`` with control characters written as escapes: a key is the client's text, and goes to a terminal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class DenialFilter:
    """Tells real denials from Zenoh's permission caching: when a client declares a key, Zenoh checks every kind
    of message on it at once and logs each refusal, right after a "caching permissions for `KEY`" line on the same
    thread. Those are not denials of anything sent; a denial of a message sent stands alone."""

    def __init__(self) -> None:
        self._caching: dict[str, str] = {}  # thread -> the key whose permissions it is caching
        self._names = Bounded()  # Zenoh id -> identity, for denials Zenoh logs by id alone (cached ones)

    def denial(self, line: str) -> tuple[str, str, str] | None:
        """``(identity, action, key)`` of a denied message in this log line, None for any other line."""
        parsed = _message(line)
        if parsed is None:
            return None
        thread, message = parsed
        subject = message.partition(_UNAUTHORIZED)[0]
        zid, name = _SUBJECT.match(subject), _identity(subject)
        if zid is not None and name:
            self._names.put(zid[1], name)
        caching = _CACHING.match(message)
        if caching is not None and thread is not None:
            self._caching[thread] = caching[1]
            return None
        if thread is not None and thread in self._caching:
            if message.endswith(f" on {self._caching[thread]}"):
                return None  # the block goes on: allowed and refused kinds of message on the same key
            del self._caching[thread]
        denial = parse_denial(line)
        cached = _CACHED.match(subject)
        if denial is not None and denial[0] == "unknown" and cached is not None:
            denial = (self._names.get(cached[1], cached[1]), *denial[1:])
        return denial


def parse_denial(line: str) -> tuple[str, str, str] | None:
    """``(identity, action, key)`` of a Zenoh ACL denial line, None for any other line. The identity is read from
    the part before "is unauthorized" only: the key after it is the client's choice, and may spell anything."""
    parsed = _message(line)
    if parsed is None:
        return None
    subject, marker, rest = parsed[1].partition(_UNAUTHORIZED)
    match = _DENIAL.match(rest) if marker else None
    if match is None or match["flow"] != "ingress":  # an egress denial mirrors an ingress one, or is routine
        return None
    return _identity(subject) or "unknown", match["action"].lower(), match["key"]


class DenialLog:
    """Reads what Zenoh writes to this process's standard output (file descriptor 1) through a pipe: Zenoh's ACL
    trace records become one line per denied (identity, action, key), every other record passes through unchanged.
    Python's own output, and the children's (:mod:`twohr_app.supervisor` hands them this process's ``sys.stdout``),
    go to the real standard output beside it, so that all that comes through the pipe is Zenoh's.

    It must never stop reading: Zenoh writes its log from the router's own threads, and a pipe nobody drains would
    block them once full. So a line it cannot handle is skipped, output to a terminal that is gone is dropped, and
    it remembers at most :data:`MAX_TRACKED` distinct denials (a client chooses its keys)."""

    def __init__(self, every: float = 10.0, out=None) -> None:
        self.every = every
        self.counts: Bounded = Bounded()  # (identity, action, key) -> times denied
        self._reported: Bounded = Bounded()  # (identity, action, key) -> the count last reported
        self._out = out
        self._filter = DenialFilter()
        self._thread: threading.Thread | None = None
        self.skipped = 0  # lines it could not handle

    def start(self) -> DenialLog:
        import zenoh

        sys.stdout.flush()
        original = os.dup(1)
        read, write = os.pipe()
        os.dup2(write, 1)
        os.close(write)
        self._out = self._out or os.fdopen(original, "w", buffering=1)
        sys.stdout = os.fdopen(os.dup(original), "w", buffering=1)
        os.environ.pop("NO_COLOR", None)  # Zenoh's ANSI escapes are what tells its records from a client's text
        zenoh.init_log_from_env_or(f"error,{ACL_TARGET}=trace")
        self._thread = threading.Thread(target=self._pump, args=(read,), name="denial-log", daemon=True)
        self._thread.start()
        return self

    def _pump(self, fd: int) -> None:
        last, acl = time.monotonic(), False
        # only a line feed ends a line: a key may hold a carriage return
        with os.fdopen(fd, "r", errors="replace", newline="\n") as lines:
            for line in lines:
                record_acl = _ACL_RECORD in line if _RECORD.match(line) else acl
                try:
                    self.feed(line, acl)
                    if time.monotonic() - last >= self.every:
                        last = time.monotonic()
                        self._summarise()
                except Exception as exc:  # the pipe must be drained, whatever a line holds
                    self.skipped += 1
                    if self.skipped == 1:
                        log.warning("denial log: a line could not be handled (%s); it goes on", _one_line(exc))
                acl = record_acl

    def feed(self, line: str, acl: bool = False) -> None:
        """Take one line Zenoh wrote; ``acl``: whether the record before it was of the ACL target. A line that does
        not start a record goes on the record before (a key with a line break): never a denial, and dropped when
        that record is an ACL one, as the record itself is."""
        if _RECORD.match(line):
            if _ACL_RECORD not in line:
                self._write(line)
                return
            denial = self._filter.denial(line)
            if denial is not None:
                count = self.counts.get(denial, 0) + 1
                self.counts.put(denial, count)
                if count == 1:
                    self._write(f"twohr router: denied {denial[0]!r} {denial[1]} on {printable(denial[2])}\n")
                    self._reported.put(denial, 1)
        elif not acl and ACL_TARGET not in line:
            self._write("  " + line)  # indented: it goes on the record before, and starts nothing

    def _summarise(self) -> None:
        for denial, count in list(self.counts.items()):
            if count > self._reported.get(denial, 0):
                self._write(f"twohr router: denied {denial[0]!r} {denial[1]} on {printable(denial[2])} {count} "
                            "times so far\n")
                self._reported.put(denial, count)

    def _write(self, text: str) -> None:
        """Write to the real standard output; once that is gone (a closed terminal, a broken pipe), drop it all."""
        try:
            self._out.write(text)
            self._out.flush()
        except (OSError, ValueError):  # ValueError: a closed file
            self._out = open(os.devnull, "w")  # kept for the process's life


class Applied(BaseModel):
    """``applied.json`` in the router's state folder: the last robots' list the router tried to put in force."""

    version: int
    ok: bool = Field(description="the router runs with this list; False: it could not, and runs with the last one "
                     "that it could (``in_force``)")
    error: str | None = None
    in_force: int = Field(description="the version of the list the router runs with")
    at: datetime.datetime


class RouterList(BaseModel):
    """The robots' list as the router's key folder holds it: ``robots.json`` and the users file made with it."""

    version: int
    robots: list[str]
    replicas: list[str] = Field(default_factory=list)
    edge: list[str] = Field(default_factory=list, description="the robots that run their own tracker")
    users: SecretStr


class ListError(ValueError):
    """A robots' list the router cannot put in force."""

    def __init__(self, version: int, reason: str) -> None:
        super().__init__(reason)
        self.version = version


def read_list(folder: Path) -> RouterList:
    """The list in ``folder`` (``robots.json`` and ``users.txt``); :class:`ListError` (with the version, when it can
    be read) for one that cannot be put in force, such as a robot id no ``twohr keys add`` makes (a line break)."""
    data = json.loads((folder / ROBOTS_FILE).read_text())
    version = int(data["version"])
    robots, replicas = list(data["robots"]), list(data.get("replicas", []))
    for name in robots:
        if not isinstance(name, str) or not ROBOT_PATTERN.fullmatch(name):
            raise ListError(version, f"{folder / ROBOTS_FILE} lists an invalid robot id {name!r}")
    for name in replicas:
        if not isinstance(name, str) or not name.isprintable() or not name or any(c in name for c in " :/"):
            raise ListError(version, f"{folder / ROBOTS_FILE} lists an invalid replica {name!r}")
    edge = [name for name in data.get("edge", []) if name in robots]
    return RouterList(version=version, robots=robots, replicas=replicas, edge=edge,
                      users=(folder / USERS_FILE).read_text())


def router_state(router_folder: Path) -> Path | None:
    """Where the router of a keys folder's ``services/router`` acknowledges lists (:meth:`Fleet.router_state`);
    None for a folder that is not inside a keys folder (a container's mount: give ``--state``)."""
    keys = Fleet(Path(router_folder).resolve().parent.parent)
    return keys.router_state if keys.exists() else None


class FleetRouter:
    """The stack's router of a fleet, run from its key folder (``<keys>/services/router``): listens on ``tls/``
    endpoints only, admits the services and the robots not revoked, each by its certificate and password, and
    restarts with the new list when ``robots.json`` changes (checked every ``poll`` s).

    In its ``state`` folder (default ``<keys>/state/router``) it keeps a lease (:data:`LEASE_FILE`, touched every
    ``poll`` s while it runs, removed when it closes) and acknowledges every list it tries (:class:`Applied` in
    :data:`APPLIED_FILE`); a list it cannot open with leaves it running with the one before, which it says there
    and in its log, and is tried again later (after ``retry`` s, then twice as long each time, up to
    :data:`RETRY_MAX`). ``twohr keys revoke`` waits for both (:func:`confirm`). The users file in force is written
    afresh for every opening into a new private folder (in ``state``, else the system's temporary folder), so a
    cleaner that empties the temporary folder while the router runs costs it nothing."""

    def __init__(self, folder: str | Path, listen: list[str], ros2_domain: int = 0, poll: float = 0.5,
                 state: str | Path | None = None, retry: float = RETRY_FIRST) -> None:
        self.folder = Path(folder)
        self.listen = listen
        self.ros2_domain = ros2_domain
        self.poll = poll
        self.retry = retry  # s before a list that failed is tried again the first time
        self.identity = load_identity(self.folder)
        self.state = Path(state) if state is not None else router_state(self.folder)
        if self.state is not None:
            try:
                private_folder(self.state)
            except OSError as exc:
                log.warning("cannot keep a lease in %s (%s)", self.state, exc)
                self.state = None
            for stale in self.state.glob("users-*") if self.state is not None else []:
                shutil.rmtree(stale, ignore_errors=True)  # a router killed before it could remove its copy
        self._private: Path | None = None  # the folder of the users file in force (0700)
        try:
            self.list = read_list(self.folder)
        except (OSError, ValueError) as exc:
            raise TwohrError(f"cannot start the fleet's router: {_one_line(exc)}") from None
        self.seen = self.list.version
        self._refused: int | None = None  # the last version whose list could not be read
        self._retry_at: float | None = None  # when to try the list of version ``seen`` again (it failed)
        self._backoff = retry
        self._last_error: str | None = None
        self.restarts = 0
        self.session = self._open(self.list)
        if self.state is not None:
            try:
                self._lease()
            except OSError as exc:
                log.warning("cannot keep a lease in %s (%s)", self.state, exc)
                self.state = None
        if self.state is None:
            log.warning("no state folder for the router of %s: twohr keys revoke cannot confirm its lists", folder)
        self._acknowledge(self.list.version, None)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="fleet-watch", daemon=True)
        self._watcher.start()

    @property
    def version(self) -> int:
        """The version of the list in force."""
        return self.list.version

    @property
    def robots(self) -> list[str]:
        """The robots of the list in force."""
        return self.list.robots

    def _open(self, listing: RouterList):
        """A router session with ``listing``'s users and access list. Its users file goes to a new private folder
        (``mkdtemp``: made by us, 0700, whatever was there before), which replaces the last one once it opened."""
        private = None
        if self.state is not None:
            with contextlib.suppress(OSError):  # one it cannot write to: the system's temporary folder
                private = Path(tempfile.mkdtemp(prefix="users-", dir=self.state))
        private = private or Path(tempfile.mkdtemp(prefix="twohr-router-"))
        try:
            users = write_private(private / USERS_FILE, listing.users.get_secret_value())
            security = RouterSecurity(users_file=users, identity=self.identity,
                                      access_control=access_control(self.ros2_domain, robots=listing.robots,
                                                                    replicas=listing.replicas, edge=listing.edge))
            session = start_router(self.listen, security)
        except BaseException:
            shutil.rmtree(private, ignore_errors=True)
            raise
        if self._private is not None:
            shutil.rmtree(self._private, ignore_errors=True)
        self._private = private
        return session

    def _watch(self) -> None:
        """Every ``poll`` s: the lease, and the list. Nothing may end this thread: the lease would go stale and the
        list unwatched, with no word said."""
        while not self._stop.wait(self.poll):
            for what, step in (("keep its lease", self._heartbeat), ("check the robots' list", self._check)):
                try:
                    step()
                    continue
                except Exception as exc:
                    error = f"{what} ({_one_line(exc)})"
                if error != self._last_error:  # once, not every poll
                    log.error("the router's watcher could not %s; it goes on", error)
                    self._last_error = error

    def _check(self) -> None:
        """Read the list; reload when it is new, when the router is down, or when a list that failed is due again."""
        try:
            listing = read_list(self.folder)
        except ListError as exc:
            if exc.version != self._refused:
                self._refused = exc.version
                log.error("robots' list version %d not applied: %s; the router goes on with version %d",
                          exc.version, exc, self.list.version)
                self._acknowledge(exc.version, str(exc))
            return
        except (OSError, ValueError, KeyError, TypeError):  # being rewritten: read it again next time
            return
        due = self._retry_at is not None and time.monotonic() >= self._retry_at
        if listing.version != self.seen or self.session is None or due:
            self.reload(listing)

    def reload(self, listing: RouterList) -> None:
        """Close the router and open it again with the robots' new list; if it cannot open with that list, open it
        again with the list it had, and say why (in the log and in :data:`APPLIED_FILE`)."""
        with self._lock:
            if listing.version != self.seen:
                self._backoff = self.retry  # a new list: its first try
            before = self.list
            gone = sorted(set(before.robots) - set(listing.robots))
            t0 = time.monotonic()
            if self.session is not None:
                self.session.close()
                self.session = None
            error = None
            try:
                self.session = self._open(listing)
                self.list = listing
            except Exception as exc:  # anything Zenoh refuses: the router must come back with the old list
                error = f"the router could not open with it: {_one_line(exc)}"
                try:
                    self.session = self._open(before)
                except Exception as again:
                    error += f"; nor with version {before.version} again: {_one_line(again)}"
            self.seen = listing.version
            self.restarts += 1
            if error is None or self.session is None:
                self._retry_at = None
                if error is not None:
                    error += f" (the router is down: tried again every {self.poll:g} s)"
            else:
                error += f" (tried again in {self._backoff:.0f} s)"
                self._retry_at = time.monotonic() + self._backoff
                self._backoff = min(2 * self._backoff, RETRY_MAX)
        self._heartbeat()
        self._acknowledge(listing.version, error)
        if error is None:
            log.warning("robots' list version %d: %s; router restarted in %.2f s", listing.version,
                        f"revoked {', '.join(gone)}" if gone else f"{len(listing.robots)} robots",
                        time.monotonic() - t0)
        else:
            log.error("robots' list version %d not applied: %s; the router goes on with version %d",
                      listing.version, error, before.version)

    def _acknowledge(self, version: int, error: str | None) -> None:
        if self.state is None:
            return
        applied = Applied(version=version, ok=error is None, error=error, in_force=self.list.version,
                          at=datetime.datetime.now(datetime.timezone.utc))
        try:
            write_private(self.state / APPLIED_FILE, applied.model_dump_json())
        except OSError as exc:
            log.warning("cannot acknowledge robots' list version %d in %s: %s", version, self.state, exc)

    def _lease(self) -> None:
        write_private(self.state / LEASE_FILE, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                                           "listen": self.listen}))

    def _heartbeat(self) -> None:
        if self.state is None:
            return
        try:
            os.utime(self.state / LEASE_FILE)
        except FileNotFoundError:
            with contextlib.suppress(OSError):
                self._lease()
        except OSError:
            pass

    @property
    def info(self):
        """The current router session's ``info`` (its Zenoh id)."""
        return self.session.info

    def close(self) -> None:
        self._stop.set()
        self._watcher.join(timeout=5)
        with self._lock:
            if self.session is not None:
                self.session.close()
        if self.state is not None:
            (self.state / LEASE_FILE).unlink(missing_ok=True)
        if self._private is not None:
            shutil.rmtree(self._private, ignore_errors=True)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def running(state: Path) -> bool:
    """Whether a fleet router keeps its lease in ``state`` (touched within :data:`LEASE_STALE` s)."""
    try:
        return time.time() - (Path(state) / LEASE_FILE).stat().st_mtime < LEASE_STALE
    except OSError:
        return False


def confirm(state: Path, version: int, timeout: float = CONFIRM_TIMEOUT) -> Applied:
    """Wait until the router that keeps its lease in ``state`` has put list ``version`` (or a later one) in force;
    :class:`FleetError` (one line) when no router runs there, when it could not apply the list, or when it says
    nothing within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        if not running(state):
            raise FleetError(f"no stack is running on these keys (no router lease in {state}): the new list is in "
                             "force when the stack starts")
        try:
            applied = Applied.model_validate_json((Path(state) / APPLIED_FILE).read_bytes())
        except (OSError, ValueError):
            applied = None
        if applied is not None and applied.version >= version:
            if applied.ok:
                return applied
            raise FleetError(f"the running stack could not apply the new list (version {applied.version}): "
                             f"{applied.error}; its router goes on with the list of version {applied.in_force}")
        if time.monotonic() > deadline:
            raise FleetError(f"the running stack did not confirm the new list (version {version}) within "
                             f"{timeout:.0f} s")
        time.sleep(0.1)
