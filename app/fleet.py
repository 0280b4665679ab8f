"""A fleet's keys: its certificate authority, one certificate per service role and per robot, and the robots' list.

``twohr keys`` (:mod:`twohr_app.commands.keys`) is the shell over this module; ``cryptography`` does every
cryptographic step (EC P-256 keys, X.509 v3 certificates signed with SHA-256). The keys folder::

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
      services/gateway/       also tokens.json: robot -> SHA-256 of its API token, robots not revoked
      robots/<robot>.crt      each robot's certificate, for audit

A robot is given one bundle file (:class:`twohr.identity.Bundle`): its certificate with the robot id as common
name, its key, the fleet CA, its bus password, its API token and the stack's endpoint.
"""

from __future__ import annotations

import datetime
import hashlib
import ipaddress
import json
import os
import secrets
from pathlib import Path

from pydantic import BaseModel, Field, SecretStr

from twohr.errors import TwohrError
from twohr.identity import CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE, Bundle, Identity, load_identity
from twohr.keys import PIPELINE_SERVICES, RESERVED_ROBOT_IDS, ROBOT_PATTERN

#: Every service role that gets its own certificate. The router and the gateway also serve TLS (the bus, HTTPS),
#: so their certificates name the hosts they are reached at.
SERVICE_ROLES = ("router", "gateway", *PIPELINE_SERVICES, "ros2")
SERVING_ROLES = ("router", "gateway")
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")
CA_DAYS, SERVICE_DAYS, ROBOT_DAYS = 3650, 825, 365


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


def token_digest(token: str) -> str:
    """The SHA-256 (hex) under which a gateway knows an API token."""
    return hashlib.sha256(token.encode()).hexdigest()


def _pem(obj) -> str:
    from cryptography.hazmat.primitives import serialization

    if hasattr(obj, "public_bytes"):
        return obj.public_bytes(serialization.Encoding.PEM).decode()
    return obj.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption()).decode()


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by its owner only, replacing it atomically; a file replaced keeps its
    owner (the service that reads it, in a container, may run as another user than whoever runs ``twohr keys``)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    if path.exists():
        before = path.stat()
        try:
            os.chown(tmp, before.st_uid, before.st_gid)
        except PermissionError:  # not root: the file becomes ours, as it would be anyway
            pass
    os.replace(tmp, path)


def _alt_names(hosts: list[str]):
    from cryptography import x509

    names = []
    for host in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host.strip("[]"))))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


class Fleet:
    """The keys folder of one fleet (see the module's docstring)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    # -- the folder ---------------------------------------------------------------------------------------------
    def exists(self) -> bool:
        return (self.folder / "ca.key").is_file() and (self.folder / "fleet.json").is_file()

    def service_folder(self, role: str) -> Path:
        return self.folder / "services" / role

    def read(self) -> FleetFile:
        if not self.exists():
            raise FleetError(f"{self.folder} holds no fleet's keys: make them with `twohr keys init {self.folder}`")
        try:
            return FleetFile.model_validate_json((self.folder / "fleet.json").read_text())
        except (OSError, ValueError) as exc:
            raise FleetError(f"{self.folder / 'fleet.json'} is unreadable: {str(exc).splitlines()[0]}") from None

    def _save(self, fleet: FleetFile) -> None:
        fleet.version += 1
        _write_private(self.folder / "fleet.json", json.dumps(_dump(fleet), indent=1))
        self._sync(fleet)

    def _sync(self, fleet: FleetFile) -> None:
        """Rewrite what the router and the gateway read from the robots' list (robots not revoked only)."""
        active = {robot: record for robot, record in fleet.robots.items() if record.revoked is None}
        router, gateway = self.service_folder("router"), self.service_folder("gateway")
        users = [f"{role}:{(self.service_folder(role) / PASSWORD_FILE).read_text().strip()}" for role in SERVICE_ROLES]
        users += [f"{robot}:{record.password.get_secret_value()}" for robot, record in active.items()]
        _write_private(router / "users.txt", "\n".join(users) + "\n")
        _write_private(gateway / "tokens.json", json.dumps({r: rec.token_sha256 for r, rec in active.items()}))
        _write_private(router / "robots.json", json.dumps({"version": fleet.version, "robots": sorted(active)}))

    # -- the CA ---------------------------------------------------------------------------------------------------
    def _ca(self):
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization

        key = serialization.load_pem_private_key((self.folder / "ca.key").read_bytes(), password=None)
        return x509.load_pem_x509_certificate((self.folder / CA_FILE).read_bytes()), key

    def issue(self, name: str, days: float, hosts: list[str] | None = None,
              not_before: datetime.datetime | None = None):
        """A new key and a certificate of the fleet CA for common name ``name`` (client and server use; ``hosts``
        as subject alternative names); returns ``(certificate, key)``."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

        ca, ca_key = self._ca()
        key = ec.generate_private_key(ec.SECP256R1())
        start = not_before or datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(minutes=5)
        builder = (x509.CertificateBuilder()
                   .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
                   .issuer_name(ca.subject).public_key(key.public_key())
                   .serial_number(x509.random_serial_number())
                   .not_valid_before(start).not_valid_after(start + datetime.timedelta(days=days))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH,
                                                         ExtendedKeyUsageOID.SERVER_AUTH]), critical=False))
        if hosts:
            builder = builder.add_extension(_alt_names(hosts), critical=False)
        return builder.sign(ca_key, hashes.SHA256()), key

    def init(self, hosts: list[str] | None = None, api_token: str | None = None) -> None:
        """Make the CA and every service role's key folder, and the operator's API token (``api_token``, else a
        new one) in the gateway's; :class:`FleetError` if the folder already holds keys."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import NameOID

        if self.exists():
            raise FleetError(f"{self.folder} already holds a fleet's keys (twohr keys list {self.folder})")
        self.folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        self.folder.chmod(0o700)
        key = ec.generate_private_key(ec.SECP256R1())
        name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "twohr fleet CA"),
                          x509.NameAttribute(NameOID.SERIAL_NUMBER, secrets.token_hex(8))])
        now = datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(minutes=5)
        ca = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
              .serial_number(x509.random_serial_number()).not_valid_before(now)
              .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
              .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
              .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                           content_commitment=False, key_encipherment=False, data_encipherment=False,
                                           key_agreement=False, encipher_only=False, decipher_only=False),
                             critical=True)
              .sign(key, hashes.SHA256()))
        _write_private(self.folder / "ca.key", _pem(key))
        (self.folder / CA_FILE).write_text(_pem(ca))
        for role in SERVICE_ROLES:
            self.issue_service(role, hosts if role in SERVING_ROLES else None)
        (self.folder / "robots").mkdir(exist_ok=True)
        _write_private(self.service_folder("gateway") / "api-token", api_token or secrets.token_urlsafe(24))
        fleet = FleetFile(version=0)
        self._save(fleet)

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
        folder = self.service_folder(role)
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        serving = list(LOCAL_NAMES) + list(hosts or []) if role in SERVING_ROLES else None
        cert, key = self.issue(role, SERVICE_DAYS, serving)
        (folder / CA_FILE).write_text((self.folder / CA_FILE).read_text())
        (folder / CERT_FILE).write_text(_pem(cert))
        _write_private(folder / KEY_FILE, _pem(key))
        if not (folder / PASSWORD_FILE).is_file():
            _write_private(folder / PASSWORD_FILE, secrets.token_urlsafe(24))
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
        """The host names and addresses the certificate of ``role`` names."""
        from cryptography import x509

        cert = x509.load_pem_x509_certificate((self.service_folder(role) / CERT_FILE).read_bytes())
        try:
            names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        except x509.ExtensionNotFound:
            return []
        return [str(n) for n in names.get_values_for_type(x509.DNSName)] + [
            str(n) for n in names.get_values_for_type(x509.IPAddress)]

    # -- robots ---------------------------------------------------------------------------------------------------
    def add(self, robot: str, out: Path, endpoint: str | None = None, days: float = ROBOT_DAYS) -> Bundle:
        """Add ``robot`` to the fleet and write its bundle to ``out`` (private, 0600)."""
        if not ROBOT_PATTERN.match(robot) or robot in RESERVED_ROBOT_IDS or robot in SERVICE_ROLES:
            taken = " (a service role's name)" if robot in SERVICE_ROLES else ""
            raise FleetError(f"invalid robot id {robot!r}{taken}: letters, digits, '_' and '-', at most 64, not "
                             f"{', '.join([*RESERVED_ROBOT_IDS, *SERVICE_ROLES])}")
        if days <= 0:
            raise FleetError(f"--days must be positive, not {days}")
        fleet = self.read()
        if robot in fleet.robots and fleet.robots[robot].revoked is None:
            raise FleetError(f"robot {robot!r} is already in the fleet (revoke it first to issue a new bundle)")
        cert, key = self.issue(robot, days)
        token, password = secrets.token_urlsafe(24), secrets.token_urlsafe(24)
        bundle = Bundle(name=robot, ca_pem=(self.folder / CA_FILE).read_text(), cert_pem=_pem(cert),
                        key_pem=SecretStr(_pem(key)), password=SecretStr(password), endpoint=endpoint,
                        api_token=SecretStr(token))
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        _write_private(out, json.dumps(_dump(bundle), indent=1))
        (self.folder / "robots" / f"{robot}.crt").write_text(bundle.cert_pem)
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


def _dump(model: BaseModel):
    """A model as JSON data with its secrets written out, for the private files that must hold them."""
    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, SecretStr):
            return value.get_secret_value()
        if isinstance(value, datetime.datetime):
            return value.isoformat()
        return value

    return plain(model.model_dump())


def active_robots(router_folder: Path) -> tuple[int, list[str]]:
    """``(version, robots not revoked)`` as the router's key folder lists them (``robots.json``)."""
    data = json.loads((Path(router_folder) / "robots.json").read_text())
    return int(data["version"]), list(data["robots"])
