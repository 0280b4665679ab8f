"""Opening Zenoh sessions from config, a router started from Python, and the health query.

A process joins the bus as a role (``TWOHR_ZENOH_USER``) with that role's password
(``TWOHR_ZENOH_PASSWORD``, or a file named by ``TWOHR_ZENOH_PASSWORD_FILE``), or from a whole Zenoh
client config file (``TWOHR_ZENOH_CONFIG``, as ``twohr up --write-client-config`` writes). On a fleet's bus it
joins with its own identity instead (``TWOHR_ZENOH_KEYS``, or ``--keys``: a key folder or a robot's bundle,
:mod:`twohr.identity`): mutual TLS with its certificate, and its password inside TLS. The router checks them,
and its access-control list (made by the composition root) decides what each identity may do.

Kept light (no numpy or OpenCV): container health checks import only this module."""

from __future__ import annotations

import ipaddress
import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import zenoh
from pydantic import BaseModel, Field, SecretStr

from . import keys
from .errors import TwohrError
from .identity import Identity, env_identity, load_identity

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


def _env_password() -> SecretStr | None:
    if path := os.environ.get("TWOHR_ZENOH_PASSWORD_FILE"):
        return SecretStr(Path(path).read_text().strip())
    value = os.environ.get("TWOHR_ZENOH_PASSWORD")
    return SecretStr(value) if value else None


def add_router_option(parser, help: str = "Zenoh router endpoint to connect to (default $TWOHR_ZENOH_ROUTER, or "
                      "the --keys bundle's)", keys: bool = True, **kwargs) -> None:
    """``--router ENDPOINT`` and ``--keys PATH``, the options every process on the bus takes (an ``argparse``
    parser)."""
    parser.add_argument("--router", default=None, metavar="ENDPOINT", help=help, **kwargs)
    if keys:
        parser.add_argument("--keys", default=None, metavar="PATH", help="join a fleet's bus with this identity: a "
                            "robot's bundle (twohr keys add) or a service's key folder (default $TWOHR_ZENOH_KEYS); "
                            "mutual TLS, to the bundle's endpoint unless --router names another")


def bus_from_args(args) -> BusConfig:
    """The :class:`BusConfig` of a process started with :func:`add_router_option`: its ``--keys`` identity (else
    the environment's), and ``--router`` when given, else the identity's endpoint, else the environment's."""
    identity = load_identity(args.keys) if getattr(args, "keys", None) else env_identity()
    router = getattr(args, "router", None) or (identity.endpoint if identity else None)
    return BusConfig(identity=identity, **({"connect": [router]} if router else {}))


class RouterSecurity(BaseModel):
    """What a router checks: the ``user:password`` file, the access-control list and, with an ``identity``, mutual
    TLS: it listens on ``tls/`` endpoints only, with that certificate, and admits only certificates of its CA."""

    users_file: Path
    access_control: dict | None = Field(None, description="None: every user admitted may do anything")
    identity: Identity | None = Field(None, description="the router's own certificate (a fleet's stack)")


class BusConfig(BaseModel):
    """How a process joins the bus. Multicast scouting is off by default: explicit endpoints only."""

    mode: Literal["client", "peer", "router"] = "client"
    connect: list[str] = Field(default_factory=lambda: [os.environ.get("TWOHR_ZENOH_ROUTER", DEFAULT_ROUTER)])
    listen: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    user: str | None = Field(default_factory=lambda: os.environ.get("TWOHR_ZENOH_USER") or None)
    password: SecretStr | None = Field(default_factory=_env_password)
    identity: Identity | None = Field(default_factory=env_identity, description="mutual TLS with this certificate "
                                      "and its credentials ($TWOHR_ZENOH_KEYS)")
    config_file: Path | None = Field(default_factory=lambda: os.environ.get("TWOHR_ZENOH_CONFIG") or None,
                                     description="a whole Zenoh config file; replaces every other field")
    security: RouterSecurity | None = Field(None, description="routers only")
    shared_memory: bool = Field(True, description="Zenoh's shared-memory transport to processes on this host; off "
                                "for clients that come and go (a camera driver): each one that used it left its pool "
                                "mapped in every receiver")

    def zenoh_config(self) -> zenoh.Config:
        if self.config_file is not None and self.mode == "client":
            try:
                return zenoh.Config.from_file(str(self.config_file))
            except Exception as exc:  # zenoh raises a bare ZError on a missing or malformed file
                reason = " ".join(str(exc).split()).split(" at /")[0]  # one line, no Rust source location
                raise TwohrError(f"invalid Zenoh config {self.config_file}: {reason}") from None
        conf: dict = {
            "mode": self.mode,
            "scouting": {"multicast": {"enabled": self.multicast_scouting}},
        }
        if self.connect:
            conf["connect"] = {"endpoints": self.connect}
        if self.listen:
            conf["listen"] = {"endpoints": self.listen}
        transport: dict = {}
        user, password = self.user, self.password
        if self.identity is not None and user is None:
            user, password = self.identity.name, self.identity.password
        if user and password is not None:
            transport["auth"] = {"usrpwd": {"user": user, "password": password.get_secret_value()}}
        if self.identity is not None:  # its certificate when it dials (a client, or a robot's router)
            for endpoint in self.connect:
                _check_keyed_link(endpoint, self.identity.name)
            transport["link"] = {"tls": self.identity.zenoh_tls()}
        if self.security is not None:
            auth = transport.setdefault("auth", {}).setdefault("usrpwd", {})
            auth["dictionary_file"] = str(self.security.users_file)
            if self.security.access_control is not None:
                conf["access_control"] = self.security.access_control
            if self.security.identity is not None:
                # a link whose peer's certificate expires is closed then, not only at the next handshake
                tls = self.security.identity.zenoh_tls(listen=True) | {"close_link_on_expiration": True}
                transport["link"] = {"protocols": ["tls"], "tls": tls}
        if not self.shared_memory:
            transport["shared_memory"] = {"enabled": False}
        if transport:
            conf["transport"] = transport
        return zenoh.Config.from_json5(json.dumps(conf))


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` (an address, or a name) reaches this host only: a loopback address, or ``localhost``. Any
    other name is not, whatever it starts with (``127.attacker.example`` resolves wherever its owner says)."""
    host = host.strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a name: it may resolve to any address
        return False


def endpoint_host(endpoint: str) -> str:
    """The host of a Zenoh endpoint (``tcp/HOST:PORT#metadata``), or ``endpoint`` itself when it is a bare host."""
    if "/" not in endpoint:
        return endpoint.strip("[]")
    address = endpoint.split("/", 1)[1].split("#", 1)[0]
    return address.rsplit(":", 1)[0].strip("[]")


def _check_keyed_link(endpoint: str, name: str) -> None:
    """A process with keys sends its password inside TLS only: a plain link (``tcp/``...) to another host is
    refused; on loopback it is a robot's own router (``twohr router --keys``), which its processes join so."""
    scheme = endpoint.partition("/")[0]
    if scheme not in ("tls", "quic", "unixsock-stream") and not is_loopback_host(endpoint_host(endpoint)):
        raise TwohrError(f"{endpoint}: {name}'s keys join over tls/HOST:PORT only (a {scheme}/ link would carry its "
                         "password in clear); plain tcp/ is for a robot's own router on loopback")


def open_session(conf: BusConfig | None = None) -> zenoh.Session:
    """A Zenoh session as ``conf`` says (default: a client of the router at $TWOHR_ZENOH_ROUTER, with the
    credentials in the environment)."""
    conf = conf or BusConfig()
    try:
        return zenoh.open(conf.zenoh_config())
    except zenoh.ZError as exc:
        reason = str(exc).split(" at /")[0]  # drop the Rust source location
        if conf.mode == "router":
            raise TwohrError(f"cannot start the Zenoh router on {', '.join(conf.listen)}: {reason}") from None
        where = conf.config_file or ", ".join(conf.connect)
        user = conf.user or (conf.identity.name if conf.identity else None)
        who = f" as {user!r}" if user else " without credentials"
        if conf.identity is not None:
            reason += (" (the router refused the TLS handshake or the credentials: a certificate of another "
                       "fleet's CA, a revoked robot, or no fleet router there)")
        raise TwohrError(f"cannot join the Zenoh bus at {where}{who}: {reason}") from None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now (for routers, gateways and tests)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def start_router(listen: list[str] | None = None, security: RouterSecurity | None = None,
                 connect: list[str] | None = None, user: str | None = None,
                 password: SecretStr | None = None, identity: Identity | None = None) -> zenoh.Session:
    """A Zenoh router inside this process, listening on ``listen`` (default tcp/127.0.0.1:7447); with
    ``security`` it admits only its users and enforces their access-control list. With ``connect`` it links to
    the routers there (retrying until they answer), presenting ``user`` and ``password`` (the ``router`` role of
    their stack, see ``twohr_app.access``) or, on a fleet's bus, ``identity``: a robot's own router carries its
    robot's identity."""
    return open_session(BusConfig(mode="router", connect=connect or [], listen=listen or [DEFAULT_ROUTER],
                                  user=user, password=password, config_file=None, identity=identity,
                                  security=security))


def replica_health(session: zenoh.Session, service: str, timeout: float = 1.0) -> list[dict]:
    """The health counters of every replica of one service that answers in time (each says its replica and host)."""
    replies = session.get(keys.health_key(service), timeout=timeout, target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE)
    answers = [json.loads(reply.ok.payload.to_bytes()) for reply in replies if reply.ok is not None]
    return sorted(answers, key=lambda answer: str(answer.get("replica", "")))


def query_health(session: zenoh.Session, service: str, timeout: float = 1.0) -> dict | None:
    """One service's health: its replicas' counters summed, each replica's own answer under ``replicas``; None if no
    replica answers in time."""
    answers = replica_health(session, service, timeout)
    if not answers:
        return None
    return merged_health(answers) | {"replicas": answers}


def merged_health(answers: list[dict]) -> dict:
    """Replicas' health answers as one: counts summed, nested counters merged the same way, lists joined without
    repeats; anything else (and each replica's name, host and pid) is the first answer's."""

    def merge(into: dict, other: dict) -> dict:
        for k, v in other.items():
            mine = into.get(k)
            if isinstance(v, int) and not isinstance(v, bool) and isinstance(mine, int) and not isinstance(mine, bool):
                into[k] = mine + v
            elif isinstance(v, dict) and isinstance(mine, dict):
                into[k] = merge(dict(mine), v)
            elif isinstance(v, list) and isinstance(mine, list):
                into[k] = mine + [item for item in v if item not in mine]
            elif k not in into:
                into[k] = v
        return into

    merged = {k: v for k, v in answers[0].items() if k not in ("replica", "host", "pid")}
    for answer in answers[1:]:
        merge(merged, {k: v for k, v in answer.items() if k not in ("replica", "host", "pid")})
    return merged


def wait_for_services(session: zenoh.Session, names: list[str], timeout: float = 30.0,
                      replicas: dict[str, set[str]] | None = None,
                      check: Callable[[], None] | None = None) -> dict[str, dict]:
    """Block until every named service answers its health query (and, for a service in ``replicas``, each of
    those replicas); raises TimeoutError naming the missing ones. ``check`` is called before each round: what it
    raises ends the wait at once (a process that was to answer has exited)."""
    deadline = time.monotonic() + timeout
    healthy: dict[str, dict] = {}
    while time.monotonic() < deadline:
        if check is not None:
            check()
        for name in names:
            if name not in healthy:
                answer = query_health(session, name, timeout=0.5)
                answered = {r.get("replica") for r in answer["replicas"]} if answer else set()
                if answer is not None and (replicas or {}).get(name, set()) <= answered:
                    healthy[name] = answer
        if len(healthy) == len(names):
            return healthy
        time.sleep(0.2)
    raise TimeoutError(f"services not healthy after {timeout:.0f} s: {sorted(set(names) - set(healthy))}")
