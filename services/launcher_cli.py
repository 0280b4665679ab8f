"""``twohr up`` and ``twohr router``: the whole system as local processes, no containers needed.

``twohr up`` starts a Zenoh router inside its own process, then every service as a subprocess
(``python -m twohr_services.<name>``) and the HTTP gateway, waits until all answer their health
query, restarts any that crashes (with backoff), and stops everything cleanly on Ctrl-C (SIGINT,
then SIGTERM, then SIGKILL after a grace). ``docker-compose.yml`` mirrors the same topology.

Secure by default: the router listens on loopback unless told otherwise, admits only the users
``twohr up`` generated for its own processes (one per role, passwords in a private folder that is
removed at exit), and enforces each role's access-control list (``twohr.access``). The HTTP API
needs a bearer token (``--api-token``) whenever the gateway listens beyond loopback; one is
generated and printed if none is given. Outside clients (camera drivers, other robots, ROS 2
nodes) join with the client config that ``--write-client-config`` writes.
"""

from __future__ import annotations

import argparse
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

from twohr.bus import add_router_option
from twohr.keys import PIPELINE_SERVICES


def _die_with_parent() -> None:
    """In a child, before exec: on Linux, have the kernel send SIGTERM when ``twohr up`` dies, even by SIGKILL,
    so that no service outlives its supervisor."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


@dataclass
class Child:
    """One supervised process: how to start it, and its restart history."""

    name: str
    args: list[str]
    env: dict[str, str]
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    restarts: int = 0
    due: float | None = None  # when a crashed child is started again

    def start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", *self.args], env=self.env, preexec_fn=_die_with_parent)
        self.started_at = time.monotonic()
        self.due = None


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

    def dead(self) -> list[tuple[str, int]]:
        return [(c.name, c.proc.returncode) for c in self.children if c.proc.poll() is not None]

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


def _wait_http(url: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(url, timeout=1) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.2)
    raise TimeoutError(f"gateway did not answer at {url} within {timeout:.0f} s")


@dataclass
class System:
    """A running stack: the in-process router, the supervised children, and the credentials of its roles."""

    router: object  # the router's zenoh.Session
    group: ProcessGroup
    endpoint: str
    credentials: object | None = field(repr=False)  # twohr.access.Credentials; None when started insecure
    secrets_dir: Path | None = None

    def bus(self, role: str = "client"):
        """A BusConfig that joins this stack as ``role``."""
        from pydantic import SecretStr

        from twohr.bus import BusConfig

        password = self.credentials.passwords[role] if self.credentials else None
        return BusConfig(connect=[self.endpoint], user=role if password else None,
                         password=SecretStr(password) if password else None, config_file=None)

    def stop(self) -> None:
        self.group.stop()
        self.router.close()
        if self.secrets_dir is not None:
            shutil.rmtree(self.secrets_dir, ignore_errors=True)


def start_system(router: str, data_roots: list[str], recordings: str, host: str, port: int,
                 api_token: str | None = None, timeout: float = 120.0, log_level: str = "INFO",
                 secure: bool = True, ros2_domain: int | None = None, foxglove_port: int | None = None,
                 record_descriptors: bool = False, maps: str | None = None) -> System:
    """Start the router, the services and the gateway; returns the :class:`System` once every part is healthy.
    With ``secure`` (the default) the router admits only generated per-role credentials and enforces the
    access-control list; ``api_token`` (None: no token) guards the HTTP API. ``foxglove_port`` turns on the
    gateway's Foxglove live view on ``host``; ``ros2_domain`` starts the ros2 service, which speaks ROS 2 over
    rmw_zenoh in that domain. ``maps``: the map store's folder (the gateway serves it)."""
    from twohr.access import Credentials, access_control
    from twohr.bus import RouterSecurity, start_router, wait_for_services

    credentials = secrets_dir = security = None
    if secure:
        credentials = Credentials.generate(api_token)
        secrets_dir = Path(tempfile.mkdtemp(prefix="twohr-secrets-"))
        credentials.save(secrets_dir)
        security = RouterSecurity(users_file=secrets_dir / "users.txt", access_control=access_control(ros2_domain or 0))
    router_session = start_router([router], security)
    system = System(router_session, ProcessGroup(), router, credentials, secrets_dir)
    base_env = {k: v for k, v in os.environ.items() if not k.startswith("TWOHR_ZENOH_")}
    base_env |= {"TWOHR_ZENOH_ROUTER": router, "TWOHR_LOG_LEVEL": log_level}

    def env(role: str) -> dict[str, str]:
        if credentials is None:
            return base_env
        return base_env | {"TWOHR_ZENOH_USER": role, "TWOHR_ZENOH_PASSWORD_FILE": str(secrets_dir / f"{role}.password")}

    try:
        roots = [arg for root in data_roots for arg in ("--data-root", root)]
        for name in PIPELINE_SERVICES:
            extra = {"source": roots, "recorder": ["--recordings", recordings] + (
                ["--record-descriptors"] if record_descriptors else [])}.get(name, [])
            system.group.start(name, [f"twohr_services.{name}", *extra], env(name))
        gateway_args = ["twohr_services.gateway", "--host", host, "--port", str(port), "--recordings", recordings,
                        *roots, "--foxglove-port", str(foxglove_port or 0), *(["--maps", maps] if maps else [])]
        gateway_env = env("gateway") | ({"TWOHR_API_TOKEN": api_token} if api_token else {})
        system.group.start("gateway", gateway_args, gateway_env)
        if ros2_domain is not None:
            system.group.start("ros2", ["twohr_services.ros2", "--domain", str(ros2_domain)], env("ros2"))
        from twohr.bus import open_session

        client = open_session(system.bus("client"))
        try:
            optional = ["ros2"] if ros2_domain is not None else []
            wait_for_services(client, [*PIPELINE_SERVICES, *optional], timeout=timeout)
        finally:
            client.close()
        _wait_http(f"http://{host}:{port}/healthz", timeout)
        if system.group.dead():
            raise RuntimeError(f"processes exited during start-up: {system.group.dead()}")
    except BaseException:
        system.stop()
        raise
    system.group.supervise()
    return system


def _up(args: argparse.Namespace) -> int:
    import secrets

    from twohr.access import write_client_config
    from twohr.errors import TwohrError

    if not args.insecure and not _loopback(args.router) and not args.expose:
        raise TwohrError(f"--router {args.router} is reachable from other hosts: add --expose to mean it "
                         "(other hosts then join with the --write-client-config file)")
    # the gateway on loopback serves only this host's users; anywhere else it needs a token
    token = args.api_token or (None if args.insecure or _loopback(args.host) else secrets.token_urlsafe(18))
    t0 = time.monotonic()
    print(f"starting router on {args.router} and services {', '.join(PIPELINE_SERVICES)} + gateway …", flush=True)
    try:
        system = start_system(args.router, args.data_root or [str(Path.cwd())], args.recordings, args.host,
                              args.port, token, args.timeout, secure=not args.insecure,
                              ros2_domain=args.ros2_domain, foxglove_port=args.foxglove_port or None,
                              record_descriptors=args.record_descriptors, maps=args.maps)
    except (TimeoutError, RuntimeError) as exc:
        raise TwohrError(str(exc)) from None
    print(f"all healthy in {time.monotonic() - t0:.1f} s — gateway http://{args.host}:{args.port} "
          f"(docs at /docs); poses on twohr/<robot>/pose; Ctrl-C stops everything", flush=True)
    if args.insecure:
        print("WARNING: --insecure: the bus admits anyone who reaches it and the HTTP API has no token",
              file=sys.stderr, flush=True)
    else:
        if token and not args.api_token:
            print(f"HTTP API token (generated): {token}   use: -H 'Authorization: Bearer {token}'", flush=True)
        client_config = write_client_config(Path(args.write_client_config), args.router, system.credentials)
        print(f"Zenoh client config for outside clients: {client_config}", flush=True)
    if args.foxglove_port:
        from twohr.foxglove_live import view_url

        print(f"live view: {view_url(args.host, args.foxglove_port)}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        stop.wait()
    finally:
        print("stopping …", flush=True)
        system.stop()
    return 0


def _loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``tcp/HOST:PORT``) or a bare host is reachable from this host only."""
    host = endpoint.split("/", 1)[-1]
    host = host.rsplit(":", 1)[0] if "/" in endpoint else host
    host = host.strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


def router_secrets(folder: Path, api_token: str | None = None):
    """The credentials kept in ``folder``, made on first use: ``credentials.json`` and the router's
    ``users.txt``, one ``<role>.password`` per role and the gateway's ``api-token``, for containers that mount
    the folder (a volume only the stack's containers see)."""
    from twohr.access import Credentials

    path = folder / "credentials.json"
    if path.is_file():
        return Credentials.load(path)
    credentials = Credentials.generate(api_token)
    credentials.save(folder)
    for item in folder.iterdir():  # readable by the stack's other users (the recorder runs as the host's uid)
        item.chmod(0o644)
    folder.chmod(0o755)
    return credentials


def _router(args: argparse.Namespace) -> int:
    from twohr.access import access_control, write_client_config
    from twohr.bus import RouterSecurity, start_router
    from twohr.errors import TwohrError

    listen = args.listen or ["tcp/0.0.0.0:7447"]
    security = None
    if not args.insecure:
        if args.secrets is None:
            raise TwohrError("give --secrets DIR (credentials are made there on first start) or --insecure")
        folder = Path(args.secrets)
        credentials = router_secrets(folder, os.environ.get("TWOHR_API_TOKEN"))
        security = RouterSecurity(users_file=folder / "users.txt", access_control=access_control(args.ros2_domain))
        write_client_config(folder / "client.json5", args.client_endpoint or listen[0], credentials).chmod(0o644)
    router = start_router(listen, security)
    print(f"zenoh router listening on {', '.join(listen)}" + (" (INSECURE)" if args.insecure else
          f", users and access control from {args.secrets}"), flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    router.close()
    return 0


def _health(args: argparse.Namespace) -> int:
    from twohr.bus import bus_from_args, open_session, query_health

    session = open_session(bus_from_args(args))
    try:
        if args.bus_only:
            print("bus ok")
            return 0
        names = args.names or list(PIPELINE_SERVICES)
        answers = {name: query_health(session, name, timeout=args.timeout) for name in names}
    finally:
        session.close()
    for name, health in answers.items():
        print(f"{name:10} " + ("NOT ANSWERING" if health is None else
                               " ".join(f"{k}={v}" for k, v in health.items() if k != "service")))
    return 0 if all(h is not None for h in answers.values()) else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start the router, every service and the gateway as local processes",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--router", default="tcp/127.0.0.1:7447", help="endpoint the Zenoh router listens on")
    p.add_argument("--data-root", action="append", help="folder sequences may come from (repeatable; default .)")
    p.add_argument("--recordings", default="recordings", help="folder for MCAP recordings")
    p.add_argument("--maps", default=None, metavar="DIR", help="the map store: sessions build, localize in and "
                   "extend the maps in this folder (POST /sessions with \"map\", GET /maps; served on "
                   "twohr/maps/<name>); kept across restarts")
    p.add_argument("--host", default="127.0.0.1", help="gateway host")
    p.add_argument("--port", type=int, default=8080, help="gateway port")
    p.add_argument("--api-token", default=None, help="bearer token the HTTP API requires (default: none on a "
                   "loopback --host; on any other host one is generated and printed)")
    p.add_argument("--write-client-config", default="runs/up/zenoh-client.json5", metavar="FILE",
                   help="where to write the Zenoh client config (router endpoint and credentials) that outside "
                   "clients, camera drivers and ROS 2 nodes use (default: %(default)s, private to you)")
    p.add_argument("--ros2-domain", type=int, default=None, metavar="ID",
                   help="also run the ros2 service: poses as ROS 2 topics (PoseStamped, Odometry, tf, Path) over "
                   "rmw_zenoh in this domain, which ROS 2 nodes with the client config can read")
    p.add_argument("--expose", action="store_true", help="allow a --router endpoint that other hosts can reach")
    p.add_argument("--insecure", action="store_true", help="no bus authentication, access control or API token "
                   "(local experiments only)")
    p.add_argument("--foxglove-port", type=int, default=8765,
                   help="Foxglove WebSocket live view on the gateway host (default 8765; 0 turns it off)")
    p.add_argument("--record-descriptors", action="store_true",
                   help="keep the raw keypoint descriptors in every recording (large)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for every service to be healthy")
    p.set_defaults(func=_up)

    p = sub.add_parser("health", help="ask services for their health counters over the bus (exit 1 if one is silent)")
    p.add_argument("names", nargs="*", help=f"services (default: {' '.join(PIPELINE_SERVICES)})")
    add_router_option(p)
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for each answer")
    p.add_argument("--bus-only", action="store_true", help="only check that the router accepts a session")
    p.set_defaults(func=_health)

    p = sub.add_parser("router", help="run a standalone Zenoh router (what the compose file's router service runs)")
    p.add_argument("--listen", action="append", default=None, help="endpoint(s), default tcp/0.0.0.0:7447")
    p.add_argument("--secrets", default=None, metavar="DIR", help="folder of the stack's credentials, made on first "
                   "start (per-role passwords, the API token, client.json5 for outside clients)")
    p.add_argument("--client-endpoint", default=None, help="router endpoint written into client.json5 (default: "
                   "the first --listen)")
    p.add_argument("--ros2-domain", type=int, default=0, help="ROS 2 domain whose rmw_zenoh keys clients may use")
    p.add_argument("--insecure", action="store_true", help="admit anyone, no access control")
    p.set_defaults(func=_router)
