"""A fleet's keys folder: its certificate authority, one certificate per service role and per robot, and the robots'
list.

``twohr keys`` (:mod:`twohr_app.commands.keys`) is the shell over :class:`Fleet`. The keys folder::

    DIR/                      private (0700): whoever holds ca.key can add robots
      ca.crt                  the fleet CA's certificate, the one issuer every process of the fleet trusts
      ca.key                  its private key (0600): needed only to add or renew a certificate (``keys add``,
                              ``add-host``, ``add-service``); ``twohr up`` and ``keys revoke`` run without it,
                              so keep it offline
      operator.token          the operator's API token (0600); the gateway's folder holds the same file
      fleet.json              the robots and the service replicas of other hosts: certificate serial and expiry,
                              revoked or not, bus password, the SHA-256 of a robot's API token (0600)
      services/<role>/        one key folder per service role (ca.crt, cert.pem, key.pem, password): the one
                              folder that service's process or container is given
      services/router/        also users.txt (the bus passwords of the services, of the replicas and of every
                              robot not revoked) and robots.json (the robots and replicas not revoked): the router
                              watches it, and a change (``twohr keys revoke``) makes it restart with the new list
      services/gateway/       also operator.token (a hard link to DIR/operator.token) and tokens.json: robot ->
                              SHA-256 of its API token and its certificate's expiry, robots not revoked
      services/gateway/grants.json  the operator's map grants (``twohr keys grant``): map -> robot -> when; a
                              robot may build or extend the maps it owns (made first) and those it is granted;
                              services/mapserver/grants.json the same file, for the map room's check of a save
      robots/<robot>.crt      each robot's certificate, for audit

A robot is given one bundle file (:class:`twohr.identity.Bundle`): its certificate with the robot id as common
name, its key, the fleet CA, its bus password, its API token and the stack's endpoint. A service replica on another
host is given a key folder of its own (``twohr keys add-service DIR ROLE HOST --out FOLDER``: FOLDER/services/ROLE,
its certificate named ``ROLE@HOST``), which ``twohr up --join ... --keys FOLDER`` runs with; it is revoked as a robot
is (``twohr keys revoke DIR ROLE@HOST``).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path

from pydantic import BaseModel, Field, SecretStr

from twohr.errors import TwohrError
from twohr.identity import (
    CA_FILE,
    CERT_FILE,
    KEY_FILE,
    PASSWORD_FILE,
    Bundle,
    Identity,
    api_token_problem,
    load_identity,
)
from twohr.keys import RESERVED_ROBOT_IDS, ROBOT_PATTERN, ROS2_RESERVED_NAMES

from . import certificates
from .certificates import pem
from .credentials import (
    SERVICE_ROLES,
    USERS_FILE,
    new_secret,
    private_folder,
    reveal,
    token_digest,
    write_private,
    write_users,
)

#: The roles whose certificates name the hosts they are reached at: they serve TLS (the bus, HTTPS).
SERVING_ROLES = ("router", "gateway")
#: The roles that read the operator's map grants, each from its own key folder: the gateway checks a session's
#: start, the map room a save
GRANT_READERS = ("gateway", "mapserver")
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")
#: listen addresses that serve every interface: the names a certificate holds, none of their own
WILDCARDS = ("0.0.0.0", "::", "")
CA_DAYS, SERVICE_DAYS, ROBOT_DAYS = 3650, 825, 365
CA_KEY_FILE, FLEET_FILE, ROBOTS_FILE, TOKENS_FILE, OPERATOR_TOKEN_FILE = (
    "ca.key", "fleet.json", "robots.json", "tokens.json", "operator.token")
#: where keys made before operator.token kept the operator's token (``keys init --if-absent`` moves it)
LEGACY_TOKEN_FILE = "api-token"
#: the keys folder's lock (:meth:`Fleet.locked`), and how long a command waits for it
LOCK_FILE, LOCK_TIMEOUT = "keys.lock", 30.0
#: a robot certificate's longest lifetime (``--days``)
MAX_ROBOT_DAYS = CA_DAYS
#: the stack's endpoint in a robot's bundle
ENDPOINT_PATTERN = re.compile(r"tls/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):[0-9]{1,5}")
#: a replica's host label, as its certificate names it (``ROLE@HOST``)
HOST_LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,62}")


class FleetError(TwohrError):
    """A keys folder or a request on it that cannot be carried out."""


class ReplicaRecord(BaseModel):
    """A service replica that joins from another host with a certificate of its own (``ROLE@HOST``), as
    ``fleet.json`` keeps it."""

    serial: str = Field(description="its certificate's serial number (hex)")
    not_after: datetime.datetime
    added: datetime.datetime
    revoked: datetime.datetime | None = None
    password: SecretStr


class RobotRecord(ReplicaRecord):
    """One robot of the fleet: a certificate and bus password as a replica's, and an API token."""

    token_sha256: str = Field(description="SHA-256 (hex) of its API token; the token itself is in its bundle only")
    edge: bool = Field(False, description="it runs its own tracker (twohr camera --edge): it may publish its own "
                       "poses, paths, status and landmarks and ask the network services for its keyframes")


class FleetFile(BaseModel):
    """``fleet.json``."""

    version: int = Field(1, description="raised by every change; the router restarts when its copy changes")
    robots: dict[str, RobotRecord] = Field(default_factory=dict)
    replicas: dict[str, ReplicaRecord] = Field(default_factory=dict, description="service replicas of other hosts, "
                                               "by certificate name ROLE@HOST")

    def active(self) -> dict[str, RobotRecord]:
        """The robots not revoked."""
        return {robot: record for robot, record in self.robots.items() if record.revoked is None}

    def active_replicas(self) -> dict[str, ReplicaRecord]:
        """The replicas not revoked."""
        return {name: record for name, record in self.replicas.items() if record.revoked is None}


class Fleet:
    """The keys folder of one fleet (see the module's docstring)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._lock_depth = 0

    # -- the folder ---------------------------------------------------------------------------------------------
    def exists(self) -> bool:
        """Whether the folder holds a fleet's keys (its CA's private key may be kept elsewhere)."""
        return (self.folder / CA_FILE).is_file() and (self.folder / FLEET_FILE).is_file()

    @property
    def operator_token(self) -> Path:
        """The operator's API token (``DIR/operator.token``)."""
        return self.folder / OPERATOR_TOKEN_FILE

    def service_folder(self, role: str) -> Path:
        return self.folder / "services" / role

    @property
    def router_state(self) -> Path:
        """Where the stack's router keeps its lease and acknowledges each robots' list (``state/router``), which
        ``twohr keys revoke`` reads, and the users file it runs with (a private copy of its folder's): no key in
        it, so a router whose key folder is read-only writes it."""
        return self.folder / "state" / "router"

    @contextlib.contextmanager
    def locked(self, timeout: float = LOCK_TIMEOUT) -> Iterator[None]:
        """Hold the keys folder's lock (``DIR/keys.lock``, ``flock``) for a read and rewrite of ``fleet.json``:
        every change (``keys add``, ``revoke``, ``renew``, ``grant``) is made under it, so that two made at once
        (two processes) cannot lose one. Re-entrant within one :class:`Fleet`."""
        import fcntl

        if self._lock_depth:
            self._lock_depth += 1
            try:
                yield
            finally:
                self._lock_depth -= 1
            return
        if not (self.folder / FLEET_FILE).is_file():
            raise FleetError(f"{self.folder} holds no fleet's keys: make them with `twohr keys init {self.folder}`")
        fd = os.open(self.folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            deadline = time.monotonic() + timeout
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise FleetError(f"{self.folder / LOCK_FILE} is held by another twohr keys command for "
                                         f"over {timeout:.0f} s: try again when it is done") from None
                    time.sleep(0.05)
            self._lock_depth = 1
            try:
                yield
            finally:
                self._lock_depth = 0
        finally:
            os.close(fd)  # closing the file releases the lock

    def read(self) -> FleetFile:
        if not self.exists():
            raise FleetError(f"{self.folder} holds no fleet's keys: make them with `twohr keys init {self.folder}`")
        try:
            return FleetFile.model_validate_json((self.folder / FLEET_FILE).read_text())
        except (OSError, ValueError) as exc:
            raise FleetError(f"{self.folder / FLEET_FILE} is unreadable: {str(exc).splitlines()[0]}") from None

    def _save(self, fleet: FleetFile, router: bool = True) -> None:
        """Write ``fleet.json`` and what is made from it; ``router=False`` for a change the router has nothing to
        load from (a renewed certificate): its list and the version stay, and it does not restart."""
        fleet.version += router
        write_private(self.folder / FLEET_FILE, json.dumps(reveal(fleet), indent=1))
        self._sync(fleet, router)

    def _sync(self, fleet: FleetFile, router_too: bool = True) -> None:
        """Rewrite what the router and the gateway read from the robots' list (robots not revoked only)."""
        active = fleet.active()
        router, gateway = self.service_folder("router"), self.service_folder("gateway")
        users = {role: (self.service_folder(role) / PASSWORD_FILE).read_text().strip() for role in SERVICE_ROLES}
        users |= {robot: record.password.get_secret_value() for robot, record in active.items()}
        replicas = fleet.active_replicas()
        users |= {name: record.password.get_secret_value() for name, record in replicas.items()}
        # each token with its certificate's expiry: the gateway refuses it after that, as the router does the link
        write_private(gateway / TOKENS_FILE, json.dumps({r: {"sha256": rec.token_sha256, "not_after": rec.not_after
                                                             .isoformat()} for r, rec in active.items()}))
        if router_too:
            write_users(router / USERS_FILE, users)
            write_private(router / ROBOTS_FILE, json.dumps({
                "version": fleet.version, "robots": sorted(active), "replicas": sorted(replicas),
                "edge": sorted(robot for robot, record in active.items() if record.edge)}))

    # -- certificates -------------------------------------------------------------------------------------------
    def issue(self, name: str, days: float, hosts: list[str] | None = None,
              not_before: datetime.datetime | None = None):
        """A new key and a certificate of the fleet CA for common name ``name`` (client and server use; ``hosts``
        as subject alternative names); returns ``(certificate, key)``. The one step that needs ``ca.key``."""
        if not (self.folder / CA_KEY_FILE).is_file():
            raise FleetError(f"{self.folder / CA_KEY_FILE} is not here: adding or renewing a certificate needs the "
                             "CA's private key; bring it back for this step (the stack and keys revoke run without it)")
        ca, ca_key = certificates.load_ca((self.folder / CA_FILE).read_bytes(),
                                          (self.folder / CA_KEY_FILE).read_bytes())
        return certificates.issue(ca, ca_key, name, days, hosts, not_before)

    def init(self, hosts: list[str] | None = None, api_token: str | None = None) -> None:
        """Make the CA and every service role's key folder, and the operator's API token (``api_token``, else a
        new one) in ``operator.token``, which the gateway's folder holds too; :class:`FleetError` if the folder
        already holds keys."""
        if self.exists():
            raise FleetError(f"{self.folder} already holds a fleet's keys (twohr keys list {self.folder})")
        if api_token is not None and (problem := api_token_problem(api_token)):
            raise FleetError(f"TWOHR_API_TOKEN: {problem}; unset it and a new one is made")
        private_folder(self.folder)
        ca, key = certificates.make_ca(CA_DAYS)
        write_private(self.folder / CA_KEY_FILE, pem(key))
        (self.folder / CA_FILE).write_text(pem(ca))  # public
        for role in SERVICE_ROLES:
            self.issue_service(role, hosts if role in SERVING_ROLES else None)
        (self.folder / "robots").mkdir(exist_ok=True)
        write_private(self.operator_token, api_token or new_secret())
        self._share_operator_token()
        self._save(FleetFile(version=0))

    def _share_operator_token(self) -> None:
        """Put ``operator.token`` in the gateway's folder too, as a hard link (one file: the gateway, given its own
        folder only, reads the token the operator reads), or a private copy where links cannot be made."""
        shared = self.service_folder("gateway") / OPERATOR_TOKEN_FILE
        shared.unlink(missing_ok=True)
        try:
            os.link(self.operator_token, shared)
        except OSError:
            write_private(shared, self.operator_token.read_text())

    def adopt_legacy_token(self) -> bool:
        """Keys made before ``operator.token`` kept the operator's token in the gateway's folder as ``api-token``:
        move it to ``operator.token``; True if it was moved."""
        legacy = self.service_folder("gateway") / LEGACY_TOKEN_FILE
        if self.operator_token.is_file() or not legacy.is_file():
            return False
        os.replace(legacy, self.operator_token)
        self._share_operator_token()
        return True

    def give(self, owners: dict[str, int]) -> None:
        """Hand each service's key folder to the user its container runs as (``role`` or ``*`` -> uid): a
        container reads its own folder only."""
        for role in SERVICE_ROLES:
            uid = owners.get(role, owners.get("*"))
            if uid is None:
                continue
            folder = self.service_folder(role)
            # a link planted in a folder is given away itself, never what it points to
            for path in (folder, *folder.iterdir()):
                os.chown(path, uid, uid, follow_symlinks=False)
            if role == "router":  # it writes its lease and acknowledgements there
                private_folder(self.router_state.parent)
                private_folder(self.router_state)
                for path in (self.router_state, *self.router_state.iterdir()):
                    os.chown(path, uid, uid, follow_symlinks=False)

    def issue_service(self, role: str, hosts: list[str] | None = None) -> Path:
        """(Re)make the key folder of service ``role``: a new certificate (for ``hosts`` besides the local names,
        for the router and the gateway), its key and a bus password kept from before."""
        folder = private_folder(self.service_folder(role))
        serving = list(LOCAL_NAMES) + list(hosts or []) if role in SERVING_ROLES else None
        cert, key = self.issue(role, SERVICE_DAYS, serving)
        (folder / CA_FILE).write_text((self.folder / CA_FILE).read_text())  # public
        (folder / CERT_FILE).write_text(pem(cert))  # public
        write_private(folder / KEY_FILE, pem(key))
        if not (folder / PASSWORD_FILE).is_file():
            write_private(folder / PASSWORD_FILE, new_secret())
        return folder

    def unnamed(self, role: str, hosts: list[str]) -> list[str]:
        """Those of ``hosts`` that the certificate of ``role`` does not name; a wildcard address (``0.0.0.0``,
        ``::``) serves the names the certificate holds, and needs none of its own."""
        have = set(self.served(role))
        return [host for host in hosts if host.strip("[]") not in have and host.strip("[]") not in WILDCARDS]

    def add_hosts(self, hosts: list[str]) -> list[str]:
        """New certificates for the router and the gateway that name ``hosts`` too (needs ``ca.key``); returns the
        names they now hold. A running stack serves them from its next start."""
        for role in SERVING_ROLES:
            self.issue_service(role, [*self.served(role), *hosts])
        return self.served("gateway")

    def served(self, role: str) -> list[str]:
        """The host names and addresses the certificate of ``role`` names."""
        return certificates.served_hosts((self.service_folder(role) / CERT_FILE).read_bytes())

    # -- robots ---------------------------------------------------------------------------------------------------
    def add(self, robot: str, out: Path, endpoint: str | None = None, days: float = ROBOT_DAYS,
            edge: bool = False) -> Bundle:
        """Add ``robot`` to the fleet and write its bundle to ``out`` (private, 0600, a new file of ours); ``edge``:
        it runs its own tracker (:attr:`RobotRecord.edge`)."""
        check_robot_id(robot)
        check_days(days)
        check_endpoint(endpoint)
        out = check_out(out)
        with self.locked():
            fleet = self.read()
            if robot in fleet.active():
                raise FleetError(f"robot {robot!r} is already in the fleet (revoke it first to issue a new bundle)")
            cert, key = self.issue(robot, days)
            token, password = new_secret(), new_secret()
            bundle = self._bundle(robot, cert, key, password, token, endpoint, out)
            now = datetime.datetime.now(datetime.timezone.utc)
            fleet.robots[robot] = RobotRecord(serial=f"{cert.serial_number:x}", not_after=cert.not_valid_after_utc,
                                              added=now, password=SecretStr(password),
                                              token_sha256=token_digest(token), edge=edge)
            self._save(fleet)
        return bundle

    def _bundle(self, robot: str, cert, key, password: str, token: str, endpoint: str | None, out: Path) -> Bundle:
        bundle = Bundle(name=robot, ca_pem=(self.folder / CA_FILE).read_text(), cert_pem=pem(cert),
                        key_pem=SecretStr(pem(key)), password=SecretStr(password), endpoint=endpoint,
                        api_token=SecretStr(token))
        out.parent.mkdir(parents=True, exist_ok=True)
        write_private(out, json.dumps(reveal(bundle), indent=1), keep_owner=False)  # a new file, ours
        (self.folder / "robots" / f"{robot}.crt").write_text(bundle.cert_pem)  # public
        return bundle

    def renew(self, robot: str, out: Path, days: float = ROBOT_DAYS, endpoint: str | None = None) -> Bundle:
        """A new certificate and key for active robot ``robot``, valid ``days`` from now, in a bundle written to
        ``out``; its bus password stays (the router has nothing new to load, the old bundle works until its
        certificate expires). Its API token stays when ``out`` is the robot's current bundle, else a new one
        replaces it. Needs ``ca.key``."""
        check_days(days)
        check_endpoint(endpoint)
        out = check_out(out)
        with self.locked():
            fleet = self.read()
            record = fleet.active().get(robot)
            if record is None:
                raise FleetError(f"no active robot {robot!r} in {self.folder} (a revoked robot is added again with "
                                 f"twohr keys add; twohr keys list {self.folder})")
            old = _own_bundle(out, robot, record)
            token = old.api_token.get_secret_value() if old is not None and old.api_token else new_secret()
            cert, key = self.issue(robot, days)
            bundle = self._bundle(robot, cert, key, record.password.get_secret_value(), token,
                                  endpoint or (old.endpoint if old is not None else None), out)
            record.serial, record.not_after = f"{cert.serial_number:x}", cert.not_valid_after_utc
            record.token_sha256 = token_digest(token)
            self._save(fleet, router=False)
        return bundle

    def revoke(self, robot: str) -> RobotRecord | ReplicaRecord:
        """Shut ``robot`` (or a service replica, ``ROLE@HOST``) out: the router drops it from its users and its
        access list when it sees the change (within a second or two), and the gateway forgets its token. Needs no
        ``ca.key``."""
        with self.locked():
            fleet = self.read()
            record = fleet.robots.get(robot) or fleet.replicas.get(robot)
            if record is None:
                raise FleetError(f"no robot {robot!r} in {self.folder}, nor a replica (twohr keys list {self.folder})")
            if record.revoked is None:
                record.revoked = datetime.datetime.now(datetime.timezone.utc)
                self._save(fleet)
        return record

    def grant(self, robot: str, map_name: str, remove: bool = False) -> list[str]:
        """Let ``robot`` build or extend map ``map_name`` though it did not build it (``remove``: take the grant
        back). The grants are ``grants.json`` in the folders of the gateway and of the map room (:data:`GRANT_READERS`),
        which a running gateway reads at its next request and the map room at its next save; no router restart.
        Needs no ``ca.key``. Returns the maps ``robot`` now holds grants on."""
        from twohr.mapstore import GRANTS_FILE, MapGrants, check_map_name

        check_map_name(map_name)  # one line for a name no map can have
        with self.locked():
            fleet = self.read()
            if not remove and robot not in fleet.active():
                raise FleetError(f"no active robot {robot!r} in {self.folder} (twohr keys list {self.folder})")
            path = self.service_folder("gateway") / GRANTS_FILE
            try:
                grants = MapGrants.model_validate_json(path.read_bytes()) if path.is_file() else MapGrants()
            except (OSError, ValueError) as exc:
                raise FleetError(f"{path} is unreadable: {str(exc).splitlines()[0]}") from None
            held = grants.maps.setdefault(map_name, {})
            if remove:
                if held.pop(robot, None) is None:
                    raise FleetError(f"robot {robot!r} holds no grant on map {map_name!r}")
                grants.maps = {name: robots for name, robots in grants.maps.items() if robots}
            else:
                held.setdefault(robot, datetime.datetime.now(datetime.timezone.utc))
            self._write_grants(grants.model_dump_json(indent=1))
            return sorted(name for name, robots in grants.maps.items() if robot in robots)

    def share_grants(self) -> bool:
        """Give the map room the gateway's grants where its copy differs (keys made before the map room checked
        saves: ``twohr up`` and ``keys init --if-absent`` call it); True if a copy was written."""
        from twohr.mapstore import GRANTS_FILE

        with self.locked():
            source = self.service_folder("gateway") / GRANTS_FILE
            copy = self.service_folder("mapserver") / GRANTS_FILE
            if not source.is_file() or (copy.is_file() and copy.read_bytes() == source.read_bytes()):
                return False
            self._write_grants(source.read_text())
            return True

    def _write_grants(self, text: str) -> None:
        """Write the grants into each of :data:`GRANT_READERS`' folders; a file made anew is given that service's
        user (a container's), as its other files are."""
        from twohr.mapstore import GRANTS_FILE

        for role in GRANT_READERS:
            folder = self.service_folder(role)
            path = folder / GRANTS_FILE
            new = not path.exists()
            write_private(path, text)
            if new:
                with contextlib.suppress(OSError):
                    reference = (folder / PASSWORD_FILE).stat()
                    os.chown(path, reference.st_uid, reference.st_gid)

    def identity(self, role: str) -> Identity:
        """The identity of service ``role``, read from its key folder."""
        return load_identity(self.service_folder(role))

    # -- service replicas of other hosts -------------------------------------------------------------------------
    def add_service(self, role: str, host: str, out: Path, days: float = ROBOT_DAYS) -> str:
        """A certificate of its own for a replica of ``role`` on ``host`` (common name ``ROLE@HOST``, the role's
        grants), written as a key folder ``out/services/<role>`` (private) for ``twohr up --join --keys out``;
        returns its name."""
        from twohr.keys import NETWORK_SERVICES

        if role not in NETWORK_SERVICES:
            raise FleetError(f"add-service {role}: replicas that join from another host are of "
                             f"{', '.join(NETWORK_SERVICES)}")
        if not HOST_LABEL.fullmatch(host):
            raise FleetError(f"invalid host {host!r}: letters, digits, '.', '_' and '-', at most 63")
        check_days(days, SERVICE_DAYS)
        name = f"{role}@{host}"
        with self.locked():
            fleet = self.read()
            if name in fleet.active_replicas():
                raise FleetError(f"replica {name!r} is already in the fleet (revoke it first to issue a new key "
                                 "folder)")
            cert, key = self.issue(name, days)
            password = new_secret()
            folder = Path(out) / "services" / role
            if folder.parent.parent.exists() and not folder.parent.parent.is_dir():
                raise FleetError(f"--out {out} is a file: name a folder (its services/{role}/ is made private)")
            folder.parent.parent.mkdir(parents=True, mode=0o700, exist_ok=True)  # one there already stays as it is
            for made in (folder.parent, folder):  # ours to narrow; --out itself may be a folder others use
                private_folder(made)
            (folder / CA_FILE).write_text((self.folder / CA_FILE).read_text())  # public
            (folder / CERT_FILE).write_text(pem(cert))  # public
            for secret, text in ((KEY_FILE, pem(key)), (PASSWORD_FILE, password)):
                write_private(folder / secret, text, keep_owner=False)  # new files, ours
            private_folder(self.folder / "replicas")
            (self.folder / "replicas" / f"{name}.crt").write_text(pem(cert))  # public, for audit
            fleet.replicas[name] = ReplicaRecord(serial=f"{cert.serial_number:x}",
                                                 not_after=cert.not_valid_after_utc,
                                                 added=datetime.datetime.now(datetime.timezone.utc),
                                                 password=SecretStr(password))
            self._save(fleet)
        return name


def check_robot_id(robot: str) -> None:
    """:class:`FleetError` unless ``robot`` may name a robot: a valid robot id (the whole of it: no line break, no
    path separator), neither reserved, a role's nor a global ROS 2 name."""
    taken = (" (a service role's name)" if robot in SERVICE_ROLES else
             " (a global ROS 2 topic, or the ros2 bridge's camera input: its namespace would be that topic)"
             if robot in ROS2_RESERVED_NAMES else "")
    if not ROBOT_PATTERN.fullmatch(robot) or robot in RESERVED_ROBOT_IDS or taken:
        raise FleetError(f"invalid robot id {robot!r}{taken}: letters, digits, '_' and '-', at most 64, not "
                         f"{', '.join([*RESERVED_ROBOT_IDS, *SERVICE_ROLES, *ROS2_RESERVED_NAMES])}")


def check_days(days: float, limit: float = MAX_ROBOT_DAYS) -> None:
    """:class:`FleetError` unless a certificate may be valid ``days`` days: more than 0, at most ``limit`` (a
    robot's :data:`MAX_ROBOT_DAYS`, a replica's :data:`SERVICE_DAYS`); NaN and infinity are neither."""
    if not 0 < days <= limit:  # False for a NaN too
        raise FleetError(f"--days {days}: give a number of days above 0 and at most {limit} (a fraction for hours "
                         "or minutes)")


def check_endpoint(endpoint: str | None) -> None:
    """:class:`FleetError` unless ``endpoint`` (the stack's router, written into a bundle) is ``tls/HOST:PORT``: a
    robot with keys sends its password over no other link."""
    if endpoint is not None and not ENDPOINT_PATTERN.fullmatch(endpoint):
        raise FleetError(f"--endpoint {endpoint!r}: give tls/HOST:PORT, the stack's router (a robot with keys "
                         "joins over TLS only: a tcp/ link would carry its password in clear)")


def check_out(out: str | Path) -> Path:
    """``out`` as a path a bundle may be written to: a file there already must be ours, since whoever owns it
    could read the key written into it (we then replace it with a new file, ours); not a folder, nor a link."""
    out = Path(out)
    try:
        st = out.lstat()
    except FileNotFoundError:
        return out
    if out.is_symlink():
        raise FleetError(f"--out {out} is a symbolic link: a robot's key is written to a file of its own, never "
                         "through a link; remove it or name another file")
    if out.is_dir():
        raise FleetError(f"--out {out} is a folder: name the bundle file to write")
    if st.st_uid != os.geteuid():
        raise FleetError(f"--out {out} belongs to user {st.st_uid}, not to you ({os.geteuid()}): whoever owns it "
                         "could read the robot's key; remove it or name another file")
    return out


def _own_bundle(out: Path, robot: str, record: RobotRecord) -> Bundle | None:
    """The robot's current bundle at ``out`` (its token's digest is the one on record), else None."""
    try:
        bundle = Bundle.model_validate_json(out.read_bytes())
    except (OSError, ValueError):
        return None
    if bundle.name != robot or bundle.api_token is None or \
            token_digest(bundle.api_token.get_secret_value()) != record.token_sha256:
        return None
    return bundle
