"""A fleet's keys folder: its certificate authority, one certificate per service role and per robot, and the robots'
list.

``twohr keys`` (:mod:`twohr_app.commands.keys`) is the shell over :class:`Fleet`. The keys folder::

    DIR/                      private (0700): whoever holds ca.key can add robots
      ca.crt                  the fleet CA's certificate, the one issuer every process of the fleet trusts
      ca.key                  its private key (0600)
      fleet.json              the robots: certificate serial and expiry, revoked or not, bus password,
                              the SHA-256 of their API token (0600)
      services/<role>/        one key folder per service role (ca.crt, cert.pem, key.pem, password): the one
                              folder that service's process or container is given
      services/router/        also users.txt (the bus passwords of the services and of every robot not revoked)
                              and robots.json (the robots not revoked): the router watches it, and a change
                              (``twohr keys revoke``) makes it restart with the new list
      services/gateway/       also api-token (the operator's) and tokens.json: robot -> SHA-256 of its API token,
                              robots not revoked
      robots/<robot>.crt      each robot's certificate, for audit

A robot is given one bundle file (:class:`twohr.identity.Bundle`): its certificate with the robot id as common
name, its key, the fleet CA, its bus password, its API token and the stack's endpoint.
"""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path

from pydantic import BaseModel, Field, SecretStr

from twohr.errors import TwohrError
from twohr.identity import CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE, Bundle, Identity, load_identity
from twohr.keys import RESERVED_ROBOT_IDS, ROBOT_PATTERN

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
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")
CA_DAYS, SERVICE_DAYS, ROBOT_DAYS = 3650, 825, 365
CA_KEY_FILE, FLEET_FILE, ROBOTS_FILE, TOKENS_FILE, API_TOKEN_FILE = (
    "ca.key", "fleet.json", "robots.json", "tokens.json", "api-token")


class FleetError(TwohrError):
    """A keys folder or a request on it that cannot be carried out."""


class RobotRecord(BaseModel):
    """One robot of the fleet, as ``fleet.json`` keeps it."""

    serial: str = Field(description="its certificate's serial number (hex)")
    not_after: datetime.datetime
    added: datetime.datetime
    revoked: datetime.datetime | None = None
    password: SecretStr
    token_sha256: str = Field(description="SHA-256 (hex) of its API token; the token itself is in its bundle only")


class FleetFile(BaseModel):
    """``fleet.json``."""

    version: int = Field(1, description="raised by every change; the router restarts when its copy changes")
    robots: dict[str, RobotRecord] = Field(default_factory=dict)

    def active(self) -> dict[str, RobotRecord]:
        """The robots not revoked."""
        return {robot: record for robot, record in self.robots.items() if record.revoked is None}


class Fleet:
    """The keys folder of one fleet (see the module's docstring)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    # -- the folder ---------------------------------------------------------------------------------------------
    def exists(self) -> bool:
        return (self.folder / CA_KEY_FILE).is_file() and (self.folder / FLEET_FILE).is_file()

    def service_folder(self, role: str) -> Path:
        return self.folder / "services" / role

    def read(self) -> FleetFile:
        if not self.exists():
            raise FleetError(f"{self.folder} holds no fleet's keys: make them with `twohr keys init {self.folder}`")
        try:
            return FleetFile.model_validate_json((self.folder / FLEET_FILE).read_text())
        except (OSError, ValueError) as exc:
            raise FleetError(f"{self.folder / FLEET_FILE} is unreadable: {str(exc).splitlines()[0]}") from None

    def _save(self, fleet: FleetFile) -> None:
        fleet.version += 1
        write_private(self.folder / FLEET_FILE, json.dumps(reveal(fleet), indent=1))
        self._sync(fleet)

    def _sync(self, fleet: FleetFile) -> None:
        """Rewrite what the router and the gateway read from the robots' list (robots not revoked only)."""
        active = fleet.active()
        router, gateway = self.service_folder("router"), self.service_folder("gateway")
        users = {role: (self.service_folder(role) / PASSWORD_FILE).read_text().strip() for role in SERVICE_ROLES}
        users |= {robot: record.password.get_secret_value() for robot, record in active.items()}
        write_users(router / USERS_FILE, users)
        write_private(gateway / TOKENS_FILE, json.dumps({r: rec.token_sha256 for r, rec in active.items()}))
        write_private(router / ROBOTS_FILE, json.dumps({"version": fleet.version, "robots": sorted(active)}))

    # -- certificates -------------------------------------------------------------------------------------------
    def issue(self, name: str, days: float, hosts: list[str] | None = None,
              not_before: datetime.datetime | None = None):
        """A new key and a certificate of the fleet CA for common name ``name`` (client and server use; ``hosts``
        as subject alternative names); returns ``(certificate, key)``."""
        ca, ca_key = certificates.load_ca((self.folder / CA_FILE).read_bytes(),
                                          (self.folder / CA_KEY_FILE).read_bytes())
        return certificates.issue(ca, ca_key, name, days, hosts, not_before)

    def init(self, hosts: list[str] | None = None, api_token: str | None = None) -> None:
        """Make the CA and every service role's key folder, and the operator's API token (``api_token``, else a
        new one) in the gateway's; :class:`FleetError` if the folder already holds keys."""
        if self.exists():
            raise FleetError(f"{self.folder} already holds a fleet's keys (twohr keys list {self.folder})")
        private_folder(self.folder)
        ca, key = certificates.make_ca(CA_DAYS)
        write_private(self.folder / CA_KEY_FILE, pem(key))
        (self.folder / CA_FILE).write_text(pem(ca))  # public
        for role in SERVICE_ROLES:
            self.issue_service(role, hosts if role in SERVING_ROLES else None)
        (self.folder / "robots").mkdir(exist_ok=True)
        write_private(self.service_folder("gateway") / API_TOKEN_FILE, api_token or new_secret())
        self._save(FleetFile(version=0))

    def give(self, owners: dict[str, int]) -> None:
        """Hand each service's key folder to the user its container runs as (``role`` or ``*`` -> uid): a
        container reads its own folder only."""
        for role in SERVICE_ROLES:
            uid = owners.get(role, owners.get("*"))
            if uid is None:
                continue
            folder = self.service_folder(role)
            for path in (folder, *folder.iterdir()):
                os.chown(path, uid, uid)

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

    def serves(self, role: str, hosts: list[str]) -> bool:
        """Whether the certificate of ``role`` names every one of ``hosts``."""
        have = set(self._served(role))
        return all(host.strip("[]") in have for host in hosts)

    def ensure_serving(self, role: str, hosts: list[str]) -> None:
        """Make sure the router's or the gateway's certificate names ``hosts``, issuing a new one if not."""
        if not self.serves(role, hosts):
            self.issue_service(role, [*self._served(role), *hosts])

    def _served(self, role: str) -> list[str]:
        return certificates.served_hosts((self.service_folder(role) / CERT_FILE).read_bytes())

    # -- robots ---------------------------------------------------------------------------------------------------
    def add(self, robot: str, out: Path, endpoint: str | None = None, days: float = ROBOT_DAYS) -> Bundle:
        """Add ``robot`` to the fleet and write its bundle to ``out`` (private, 0600)."""
        check_robot_id(robot)
        if days <= 0:
            raise FleetError(f"--days must be positive, not {days}")
        fleet = self.read()
        if robot in fleet.active():
            raise FleetError(f"robot {robot!r} is already in the fleet (revoke it first to issue a new bundle)")
        cert, key = self.issue(robot, days)
        token, password = new_secret(), new_secret()
        bundle = Bundle(name=robot, ca_pem=(self.folder / CA_FILE).read_text(), cert_pem=pem(cert),
                        key_pem=SecretStr(pem(key)), password=SecretStr(password), endpoint=endpoint,
                        api_token=SecretStr(token))
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_private(out, json.dumps(reveal(bundle), indent=1))
        (self.folder / "robots" / f"{robot}.crt").write_text(bundle.cert_pem)  # public
        now = datetime.datetime.now(datetime.timezone.utc)
        fleet.robots[robot] = RobotRecord(serial=f"{cert.serial_number:x}", not_after=cert.not_valid_after_utc,
                                          added=now, password=SecretStr(password), token_sha256=token_digest(token))
        self._save(fleet)
        return bundle

    def revoke(self, robot: str) -> RobotRecord:
        """Shut ``robot`` out: the router drops it from its users and its access list when it sees the change
        (within a second or two), and the gateway forgets its token."""
        fleet = self.read()
        record = fleet.robots.get(robot)
        if record is None:
            raise FleetError(f"no robot {robot!r} in {self.folder} (twohr keys list {self.folder})")
        if record.revoked is None:
            record.revoked = datetime.datetime.now(datetime.timezone.utc)
            self._save(fleet)
        return record

    def identity(self, role: str) -> Identity:
        """The identity of service ``role``, read from its key folder."""
        return load_identity(self.service_folder(role))


def check_robot_id(robot: str) -> None:
    """:class:`FleetError` unless ``robot`` may name a robot: a valid robot id, neither reserved nor a role's."""
    if not ROBOT_PATTERN.match(robot) or robot in RESERVED_ROBOT_IDS or robot in SERVICE_ROLES:
        taken = " (a service role's name)" if robot in SERVICE_ROLES else ""
        raise FleetError(f"invalid robot id {robot!r}{taken}: letters, digits, '_' and '-', at most 64, not "
                         f"{', '.join([*RESERVED_ROBOT_IDS, *SERVICE_ROLES])}")


def active_robots(router_folder: Path) -> tuple[int, list[str]]:
    """``(version, robots not revoked)`` as the router's key folder lists them (``robots.json``)."""
    data = json.loads((Path(router_folder) / ROBOTS_FILE).read_text())
    return int(data["version"]), list(data["robots"])
