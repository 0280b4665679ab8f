"""The stack as local processes: a Zenoh router inside this process, every service as a supervised child
(``python -m twohr_services.<name>``) and the HTTP gateway.

:func:`start_system` waits until every part answers its health query; :class:`ProcessGroup` restarts a child
that crashes (with backoff) and stops them all together (SIGTERM, then SIGKILL after a grace). ``twohr up``
(:mod:`twohr_app.commands.up`) runs it until Ctrl-C; the tests and the lab's live benches start it directly.
``docker-compose.yml`` mirrors the same topology.

Secure by default: the router admits only the users generated here for the stack's own processes (one per
role, passwords in a private folder that is removed at exit) and enforces each role's access-control list
(:mod:`twohr_app.access`); :mod:`twohr_app.fleet` makes and writes the credentials.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

from twohr.keys import PIPELINE_SERVICES

from .fleet import USERS_FILE, Credentials, Fleet, password_file
from .fleet.store import OPERATOR_TOKEN_FILE

#: the audit trail's file in the map store's folder (:func:`audit_file`)
AUDIT_FILE = "audit.jsonl"


def audit_file(maps: str | Path) -> Path:
    """The audit trail of a stack whose map store is ``maps``: ``<maps>/audit.jsonl``, where ``twohr up`` has the
    gateway and the map room write it, compose keeps it (``/maps/audit.jsonl``) and ``twohr maps rollback``
    appends by default."""
    return Path(maps) / AUDIT_FILE


def _die_with_parent() -> None:
    """In a child, before exec: on Linux, have the kernel send SIGTERM when ``twohr up`` dies, even by SIGKILL,
    so that no service outlives its supervisor."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _stdout_fd() -> int | None:
    """Where this process's ``print`` goes, for a child's standard output (None: inherit file descriptor 1). Under
    :class:`~twohr_app.fleet_router.DenialLog` descriptor 1 carries Zenoh's log alone, and a child's output there
    would pass for Zenoh's."""
    try:
        return sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # a test's captured stdout: no descriptor of its own
        return None


#: how long children that were still starting get to exit when the stack's start fails (then SIGKILL)
STARTING_GRACE_S = 1.0
#: how long a child's last lines, written as it exited, may take to come through its standard error's pipe
LAST_WORDS_S = 2.0


@dataclass
class Child:
    """One supervised process: how to start it, its restart history, and the last line it wrote to its standard
    error (which passes through this process's, line by line)."""

    name: str
    args: list[str]
    env: dict[str, str]
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    restarts: int = 0
    due: float | None = None  # when a crashed child is started again
    last_line: str = ""
    relay: threading.Thread | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", *self.args], env=self.env, preexec_fn=_die_with_parent,
                                     stdout=_stdout_fd(), stderr=subprocess.PIPE)
        self.started_at = time.monotonic()
        self.due = None
        self.last_line = ""
        self.relay = threading.Thread(target=self._relay_stderr, args=(self.proc.stderr,),
                                      name=f"{self.name}-stderr", daemon=True)
        self.relay.start()

    def _relay_stderr(self, stream) -> None:
        """Pass the child's standard error on to ours, keeping its last line. It never stops reading before the
        child closes it (a pipe nobody drains would block the child once full): output to a terminal that is gone
        is dropped."""
        with stream:
            for raw in stream:
                line = raw.decode(errors="replace")
                if line.strip():
                    self.last_line = line.strip()
                try:
                    sys.stderr.write(line)
                    sys.stderr.flush()
                except (OSError, ValueError):
                    pass

    def exit_line(self) -> str:
        """Why the child exited, in one line: its exit code and the last line it wrote to its standard error."""
        if self.relay is not None:
            self.relay.join(LAST_WORDS_S)
        said = f": {self.last_line}" if self.last_line else " and said nothing"
        return f"{self.name} exited with code {self.proc.returncode} during start-up{said}"


@dataclass
class ProcessGroup:
    """Child processes that are supervised together: a crashed one is restarted after a backoff (1 s, doubling
    up to ``max_backoff`` while it keeps crashing within ``stable_after`` s of its start), and all are stopped
    together, in reverse start order."""

    max_backoff: float = 30.0
    stable_after: float = 60.0
    children: list[Child] = field(default_factory=list)
    stopping: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def start(self, name: str, args: list[str], env: dict[str, str]) -> subprocess.Popen:
        child = Child(name, args, env)
        child.start()
        with self.lock:
            self.children.append(child)
        return child.proc

    def pid(self, name: str) -> int:
        return next(c.proc.pid for c in self.children if c.name == name)

    def check_started(self) -> None:
        """RuntimeError (one line: the first to exit, and the last line it wrote) if a child has exited: called while
        the stack starts, when nothing restarts a child yet and each one is needed."""
        with self.lock:
            exited = next((child for child in self.children if child.proc.poll() is not None), None)
        if exited is not None:
            raise RuntimeError(exited.exit_line())

    def supervise_once(self) -> list[str]:
        """Schedule restarts of crashed children and start those that are due; returns the names restarted."""
        now, restarted = time.monotonic(), []
        with self.lock:
            for child in self.children:
                if self.stopping.is_set() or child.proc.poll() is None:
                    continue
                if child.due is None:
                    if now - child.started_at > self.stable_after:
                        child.restarts = 0
                    backoff = min(self.max_backoff, 2.0 ** child.restarts)
                    child.due = now + backoff
                    print(f"twohr: {child.name} exited with code {child.proc.returncode}; restarting in "
                          f"{backoff:.0f} s", file=sys.stderr, flush=True)
                elif now >= child.due:
                    child.restarts += 1
                    child.start()
                    restarted.append(child.name)
        return restarted

    def supervise(self, interval: float = 0.5) -> threading.Thread:
        """Run :meth:`supervise_once` on a background thread until :meth:`stop`."""
        def loop() -> None:
            while not self.stopping.wait(interval):
                self.supervise_once()
        thread = threading.Thread(target=loop, name="supervisor", daemon=True)
        thread.start()
        return thread

    def stop(self, grace: float = 10.0) -> None:
        self.stopping.set()
        with self.lock:
            procs = [c.proc for c in self.children]
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for proc in procs:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _wait_http(group: ProcessGroup, base: str, timeout: float, fleet: Fleet | None = None) -> None:
    """Until the gateway answers ``/healthz``; RuntimeError at once when a child exits meanwhile."""
    import ssl

    url = f"{base}/healthz"
    context = ssl.create_default_context(cafile=str(fleet.folder / "ca.crt")) if fleet else None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        group.check_started()
        try:
            with urllib.request.urlopen(url, timeout=1, context=context) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.2)
    raise TimeoutError(f"gateway did not answer at {url} within {timeout:.0f} s")


@dataclass
class StackAccess:
    """How the stack's own processes prove who they are: nothing (insecure), per-role passwords generated for this
    run (kept in a private folder removed at exit), or a fleet's keys (each process its own key folder)."""

    credentials: Credentials | None = field(default=None, repr=False)
    secrets_dir: Path | None = None
    keys: Fleet | None = None

    @classmethod
    def generated(cls) -> StackAccess:
        credentials = Credentials.generate()
        secrets_dir = Path(tempfile.mkdtemp(prefix="twohr-secrets-"))
        credentials.save(secrets_dir)
        return cls(credentials=credentials, secrets_dir=secrets_dir)

    def env(self, role: str) -> dict[str, str]:
        """The environment that makes a child process join as ``role``."""
        if self.keys is not None:
            return {"TWOHR_ZENOH_KEYS": str(self.keys.service_folder(role))}
        if self.credentials is not None:
            return {"TWOHR_ZENOH_USER": role, "TWOHR_ZENOH_PASSWORD_FILE": str(password_file(self.secrets_dir, role))}
        return {}

    def bus(self, role: str, endpoint: str):
        """A BusConfig that joins the stack at ``endpoint`` as ``role``."""
        from pydantic import SecretStr

        from twohr.bus import BusConfig

        if self.keys is not None:
            return BusConfig(connect=[endpoint], identity=self.keys.identity(role), config_file=None, user=None,
                             password=None)
        password = self.credentials.passwords[role] if self.credentials else None
        return BusConfig(connect=[endpoint], user=role if password else None, identity=None,
                         password=SecretStr(password) if password else None, config_file=None)

    def close(self) -> None:
        if self.secrets_dir is not None:
            shutil.rmtree(self.secrets_dir, ignore_errors=True)


@dataclass
class System:
    """A running stack: its router (a Zenoh session, or a :class:`~twohr_app.fleet_router.FleetRouter` on a fleet's
    keys), the supervised children, and how its processes join."""

    router: object
    group: ProcessGroup
    endpoint: str
    access: StackAccess
    replicas: dict[str, set[str]] = field(default_factory=dict)  # service -> the replicas started here

    @property
    def credentials(self):
        return self.access.credentials

    def bus(self, role: str = "client"):
        """A BusConfig that joins this stack as ``role`` (a service role's key folder on a fleet's keys)."""
        return self.access.bus(role, self.endpoint)

    def stop(self, grace: float = 10.0) -> None:
        """Stop every child (SIGTERM, SIGKILL after ``grace`` s), then the router."""
        self.group.stop(grace)
        self.router.close()
        self.access.close()


def _start_router(endpoint: str, access: StackAccess, ros2_domain: int):
    from twohr.bus import RouterSecurity, start_router

    from .access import access_control

    if access.keys is not None:
        from .fleet_router import FleetRouter

        return FleetRouter(access.keys.service_folder("router"), [endpoint], ros2_domain)
    if access.credentials is None:
        return start_router([endpoint])
    return start_router([endpoint], RouterSecurity(users_file=access.secrets_dir / USERS_FILE,
                                                   access_control=access_control(ros2_domain)))


def _endpoint_host(endpoint: str) -> str:
    return endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")


def local_host(host: str) -> str:
    """``host``, or the loopback address where ``host`` is a wildcard (``0.0.0.0``, ``::``): where a process of
    this host reaches a server listening on ``host``, by a name its certificate holds."""
    return {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(host.strip("[]"), host)


def local_endpoint(endpoint: str) -> str:
    """A Zenoh endpoint to dial for one that listens on ``endpoint`` (a wildcard address becomes loopback)."""
    host = _endpoint_host(endpoint)
    local = local_host(host)
    if local == host:
        return endpoint
    protocol, _, address = endpoint.partition("/")
    return f"{protocol}/{'[::1]' if local == '::1' else local}:{address.rsplit(':', 1)[1]}"


def check_custody(fleet: Fleet, router: str, hosts: list[str], api_token: str | None = None) -> None:
    """One line (:class:`~twohr_app.fleet.FleetError`) unless the stack can run on ``fleet``'s keys as they are,
    without the CA's private key: the router listens on ``tls/``, the router's and the gateway's certificates name
    their hosts (a wildcard serves the names they hold), and the operator's token is in ``operator.token``, not on a
    command line."""
    from .fleet import FleetError

    fleet.read()  # one clear line for a folder without keys
    if not router.startswith("tls/"):
        raise FleetError(f"--router {router}: on a fleet's keys the stack's router listens on tls/HOST:PORT only (a "
                         "robot's password crosses no plain link)")
    if api_token is not None:
        raise FleetError(f"on a fleet's keys the operator's API token is {fleet.operator_token} (twohr keys init "
                         "wrote it): give no --api-token")
    if not (fleet.service_folder("gateway") / OPERATOR_TOKEN_FILE).is_file():
        raise FleetError(f"{fleet.folder} holds no operator.token (keys made before it): run twohr keys init "
                         f"{fleet.folder} --if-absent, which moves the token there")
    for role, wanted in (("router", [_endpoint_host(router)]), ("gateway", hosts)):
        if missing := fleet.unnamed(role, wanted):
            raise FleetError(f"the {role}'s certificate does not name {', '.join(missing)} (it names "
                             f"{', '.join(fleet.served(role))}): add it with twohr keys add-host {fleet.folder} "
                             f"{' '.join(missing)} (needs {fleet.folder / 'ca.key'})")


def start_system(router: str, data_roots: list[str], recordings: str, host: str, port: int,
                 api_token: str | None = None, timeout: float = 120.0, log_level: str = "INFO",
                 secure: bool = True, ros2_domain: int | None = None, foxglove_port: int | None = None,
                 record_descriptors: bool = False, maps: str | None = None, keys: str | Path | None = None,
                 hosts: list[str] | None = None, replicas: dict[str, int] | None = None,
                 max_robots: float | None = None, map_versions: int | None = None) -> System:
    """Start the router, the services and the gateway; returns the :class:`System` once every part is healthy.
    With ``secure`` (the default) the router admits only generated per-role credentials and enforces the
    access-control list; with ``keys`` (a fleet's keys folder, ``twohr keys init``) every link is mutual TLS
    instead, each process with its own certificate, one identity per robot, the gateway on HTTPS for ``host``
    and ``hosts``, names their certificates must hold (the CA's private key is not read). ``api_token`` (None: no
    token) guards the HTTP API; on ``keys`` the operator's token is theirs (``operator.token``) and ``api_token``
    stays None. ``foxglove_port`` turns on the
    gateway's Foxglove live view on ``host`` (with ``keys`` on TLS, and a viewer needs a token);
    ``ros2_domain`` starts the ros2 service, which speaks ROS 2 over rmw_zenoh in that domain. ``maps``: the map
    store's folder (the map room serves it on the bus, the gateway over HTTP; both keep the audit trail there:
    :func:`audit_file`). ``replicas``: how
    many processes of each network service to run (:func:`check_replicas`; default one each, and one tracker
    per admitted robot: :func:`trackers_for`). ``max_robots``: the gateway's admission limit (None: none).
    ``map_versions``: versions of each map the store keeps (None: the store's default, 10)."""

    if keys is not None:
        fleet = Fleet(keys)
        check_custody(fleet, router, [host, *(hosts or [])], api_token)
        fleet.share_grants()  # keys made before the map room read the grants: its copy
        access = StackAccess(keys=fleet)
    else:
        access = StackAccess.generated() if secure else StackAccess()
    listen, router = router, local_endpoint(router)  # the stack's own processes dial it on this host
    system = System(_start_router(listen, access, ros2_domain or 0), ProcessGroup(), router, access)
    base_env = _child_env(router, log_level)
    try:
        roots = [arg for root in data_roots for arg in ("--data-root", root)]
        counts = {name: 1 for name in PIPELINE_SERVICES} | trackers_for(max_robots) | check_replicas(replicas or {})
        started = {}
        for name in PIPELINE_SERVICES:
            extra = {"source": roots, "recorder": ["--recordings", recordings] + (
                ["--record-descriptors"] if record_descriptors else []),
                "tracker": ["--shared-cores"] if counts["tracker"] > 1 else [],
                "mapserver": _map_room_args(maps, map_versions, access.keys)}.get(name, [])
            started[name] = start_replicas(system.group, name, counts[name], extra, base_env | access.env(name))
        gateway_args = ["twohr_services.gateway", "--host", host, "--port", str(port), "--recordings", recordings,
                        *roots, "--foxglove-port", str(foxglove_port or 0),
                        *(["--maps", maps, "--audit-log", str(audit_file(maps))] if maps else []),
                        *(_gateway_tls_args(access.keys) if access.keys else []),
                        *(["--max-robots", f"{max_robots:g}"] if max_robots else []),
                        *(["--map-versions", str(map_versions)] if map_versions else [])]
        gateway_env = base_env | access.env("gateway") | ({"TWOHR_API_TOKEN": api_token} if api_token else {})
        system.group.start("gateway", gateway_args, gateway_env)
        if ros2_domain is not None:
            system.group.start("ros2", ["twohr_services.ros2", "--domain", str(ros2_domain)],
                               base_env | access.env("ros2"))
        optional = ["ros2"] if ros2_domain is not None else []
        _wait_ready(system, system.bus("gateway" if access.keys else "client"), [*PIPELINE_SERVICES, *optional],
                    started, timeout)
        _wait_http(system.group, gateway_url(local_host(host), port, access.keys), timeout, access.keys)
        system.group.check_started()
    except BaseException:
        system.stop(STARTING_GRACE_S)  # a child still starting has nothing to finish
        raise
    system.group.supervise()
    return system


def _child_env(router: str, log_level: str) -> dict[str, str]:
    """The environment of every child: this process's, without its bus identity or an API token (the gateway
    alone is given the token), joined to ``router``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWOHR_ZENOH_") and k != "TWOHR_API_TOKEN"}
    return env | {"TWOHR_ZENOH_ROUTER": router, "TWOHR_LOG_LEVEL": log_level}


def _wait_ready(system: System, bus, names: list[str], started: dict[str, set[str]], timeout: float) -> None:
    """Until every service in ``names``, and each replica ``started`` here, answers its health query (asked as
    ``bus``); the system then knows its replicas. RuntimeError at once when a child exits meanwhile."""
    from twohr.bus import open_session, wait_for_services

    client = open_session(bus)
    try:
        wait_for_services(client, names, timeout=timeout, replicas=started, check=system.group.check_started)
        system.replicas = started
    finally:
        client.close()


def trackers_for(max_robots: float | None) -> dict[str, int]:
    """``{"tracker": N}``: one tracker for each robot the stack admits (a half robot, at 15 Hz, still needs one),
    so that no robot's per-frame work waits on another's; empty without a limit (one tracker)."""
    return {"tracker": max(1, math.ceil(max_robots - 1e-9))} if max_robots else {}


def check_replicas(replicas: dict[str, int], trackers: bool = True) -> dict[str, int]:
    """``replicas`` checked: only the network services and (``trackers``) the tracker run as several processes,
    each at least once; a :class:`~twohr.errors.ConfigError` in one line otherwise."""
    from twohr.errors import ConfigError
    from twohr.keys import NETWORK_SERVICES

    allowed = (*NETWORK_SERVICES, "tracker") if trackers else NETWORK_SERVICES
    for name, count in replicas.items():
        if name not in allowed:
            why = ("runs in the stack, not joined to it (a robot tracks itself with twohr camera --edge)"
                   if name == "tracker" else
                   "is not a network service" if name in PIPELINE_SERVICES else "is no service")
            raise ConfigError(f"replicas of {name!r}: {name} {why}; replicas are for {', '.join(allowed)}")
        if count < 1:
            raise ConfigError(f"{name}={count}: a service needs at least one replica (leave it out of --only "
                              "instead)")
    return dict(replicas)


def start_replicas(group: ProcessGroup, name: str, count: int, args: list[str], env: dict[str, str]) -> set[str]:
    """Start ``count`` processes of service ``name`` (``detector``, ``detector-2``, …), each its own replica named
    ``<host>-<supervisor pid>-<child>`` (a restarted child comes back as the same replica); returns the names."""
    import socket

    names = set()
    for i in range(count):
        child = name if i == 0 else f"{name}-{i + 1}"
        names.add(replica := f"{socket.gethostname()}-{os.getpid()}-{child}")
        group.start(child, [f"twohr_services.{name}", *args], env | {"TWOHR_REPLICA": replica})
    return names


def join_stack(router: str, services: dict[str, int], keys: str | Path | None, timeout: float = 120.0,
               log_level: str = "INFO") -> System:
    """Replicas of network services on this host, joined to a running stack's router at ``router``: with
    ``keys`` (a fleet's keys, or a folder holding ``services/<role>/`` for each service started) each with its
    service's certificate; without, with no credentials (a stack started ``--insecure``). Returns once each
    replica answers its health query."""

    counts = check_replicas(services)
    access = StackAccess(keys=Fleet(keys)) if keys else StackAccess()
    if access.keys is not None:
        from twohr.errors import ConfigError

        missing = [name for name in counts if not access.keys.service_folder(name).is_dir()]
        if missing:
            raise ConfigError(f"{keys} holds no key folder for {', '.join(missing)} (services/<role>/, as "
                              "`twohr keys add-service KEYS ROLE HOST --out FOLDER` makes them)")
    base_env = _child_env(router, log_level)
    system = System(_NoRouter(), ProcessGroup(), router, access)
    try:
        started = {name: start_replicas(system.group, name, count, [], base_env | access.env(name))
                   for name, count in counts.items()}
        _wait_ready(system, access.bus(next(iter(counts)), router), list(counts), started, timeout)
        system.group.check_started()
    except BaseException:
        system.stop(STARTING_GRACE_S)  # a child still starting has nothing to finish
        raise
    system.group.supervise()
    return system


class _NoRouter:
    """A joining host runs no router of its own."""

    def close(self) -> None:
        pass


def _map_room_args(maps: str | None, map_versions: int | None, fleet: Fleet | None) -> list[str]:
    """The map room's store: the gateway's folder and audit trail, and on a fleet's keys the operator's map grants
    in the map room's own key folder (``twohr keys grant`` writes them there too)."""
    from twohr.mapstore import GRANTS_FILE

    if not maps:
        return []
    return ["--maps", maps, "--audit-log", str(audit_file(maps)),
            *(["--map-versions", str(map_versions)] if map_versions else []),
            *(["--map-grants", str(fleet.service_folder("mapserver") / GRANTS_FILE)] if fleet else [])]


def _gateway_tls_args(fleet: Fleet) -> list[str]:
    folder = fleet.service_folder("gateway")  # its own folder, as every child is given only its own
    return ["--tls-keys", str(folder), "--robot-tokens", str(folder / "tokens.json"), "--api-token-file",
            str(folder / OPERATOR_TOKEN_FILE)]


def gateway_url(host: str, port: int, fleet: Fleet | None = None) -> str:
    """The gateway's base URL: HTTPS on a fleet's keys."""
    return f"{'https' if fleet else 'http'}://{host}:{port}"
