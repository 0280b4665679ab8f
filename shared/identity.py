"""Who a process is on a fleet's bus: its certificate and key, the fleet's CA, its user name and password and,
for a robot, the stack's endpoint and its API token.

``twohr keys`` (``twohr_app.fleet``) makes two forms of it:

- a service's key folder, ``<keys>/services/<role>/`` (``ca.crt``, ``cert.pem``, ``key.pem``, ``password``), the
  one folder that service's process or container is given;
- a robot's bundle, one private JSON file (``twohr keys add DIR ROBOT --out BUNDLE``), the one file a robot is given.

:func:`load_identity` reads either, and checks what can be checked without the stack (readable, a certificate of
the bundle's CA, not expired, the key matching it), so that a bad one is one line at start, not a client that
retries in silence. ``TWOHR_ZENOH_KEYS`` names the identity a process joins the bus with.
"""

from __future__ import annotations

import base64
import datetime
import json
import os
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, SecretStr, ValidationError

from .errors import TwohrError, validation_problems

BUNDLE_KIND = "twohr-robot-bundle"
#: The files of a service's key folder.
CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE = "ca.crt", "cert.pem", "key.pem", "password"
#: the shortest API token a gateway or ``twohr keys init`` accepts (a generated one has 32 characters)
MIN_TOKEN_CHARS = 16


def api_token_problem(token: str) -> str | None:
    """Why ``token`` cannot be an API token (blank, shorter than :data:`MIN_TOKEN_CHARS`, or with spaces: a header
    would not carry it as it is), or None when it can."""
    if not token.strip():
        return "the API token is empty: a blank token would let in a request with no token at all"
    if len(token) < MIN_TOKEN_CHARS or any(c.isspace() for c in token):
        return f"the API token must have at least {MIN_TOKEN_CHARS} characters and no spaces (it has {len(token)})"
    return None


class IdentityError(TwohrError):
    """A key folder or bundle that cannot be used: missing, corrupt, expired, or not of its own CA."""


class Identity(BaseModel):
    """A certificate of the fleet's CA with its key, and the bus credentials that go with it."""

    name: str = Field(description="the certificate's common name: a robot id or a service role")
    ca_pem: str = Field(description="the fleet CA's certificate (PEM): the only issuer this process trusts")
    cert_pem: str
    key_pem: SecretStr
    password: SecretStr = Field(description="the bus password of ``name`` (Zenoh usrpwd, only ever sent inside TLS)")
    endpoint: str | None = Field(None, description="the stack's router, tls/HOST:PORT (a robot's bundle)")
    api_token: SecretStr | None = Field(None, description="the robot's token for the stack's HTTP API")

    def zenoh_tls(self, listen: bool = False) -> dict:
        """The ``transport.link.tls`` section: mutual TLS with this certificate (also as the listening side's
        with ``listen``), trusting the fleet CA alone."""
        def b64(text: str) -> str:
            return base64.b64encode(text.encode()).decode()

        tls = {"root_ca_certificate_base64": b64(self.ca_pem), "enable_mtls": True,
               "connect_certificate_base64": b64(self.cert_pem),
               "connect_private_key_base64": b64(self.key_pem.get_secret_value())}
        if listen:
            tls |= {"listen_certificate_base64": b64(self.cert_pem),
                    "listen_private_key_base64": b64(self.key_pem.get_secret_value())}
        return tls


class Bundle(Identity):
    """A robot's bundle as stored: an :class:`Identity` with its kind and format version."""

    kind: Literal["twohr-robot-bundle"] = BUNDLE_KIND
    version: Literal[1] = 1


def load_identity(path: str | Path, now: datetime.datetime | None = None) -> Identity:
    """The identity in a service's key folder or a robot's bundle file, checked (:func:`check_identity`);
    :class:`IdentityError` in one line for anything unusable."""
    path = Path(path)
    if path.is_dir():
        files = {name: path / name for name in (CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE)}
        missing = [name for name, file in files.items() if not file.is_file()]
        if missing:
            raise IdentityError(f"key folder {path} lacks {', '.join(missing)}")
        texts = {name: _read(file) for name, file in files.items()}
        # the folder's name is where it is mounted (a container sees /run/twohr/keys): the certificate says who
        identity = Identity(name=_common_name(texts[CERT_FILE], path), ca_pem=texts[CA_FILE], cert_pem=texts[CERT_FILE],
                            key_pem=SecretStr(texts[KEY_FILE]), password=SecretStr(texts[PASSWORD_FILE].strip()))
    elif path.is_file():
        try:
            identity = Bundle.model_validate(json.loads(_read(path)))
        except json.JSONDecodeError as exc:
            raise IdentityError(f"{path} is not a twohr bundle: not JSON ({exc.msg}, line {exc.lineno})") from None
        except ValidationError as exc:
            raise IdentityError(f"{path} is not a twohr bundle: {validation_problems(exc)}") from None
    else:
        raise IdentityError(f"key file not found: {path}")
    check_identity(identity, str(path), now)
    return identity


def check_identity(identity: Identity, where: str, now: datetime.datetime | None = None) -> None:
    """Raise :class:`IdentityError` unless the certificate parses, names ``identity.name``, was signed by the
    identity's CA, is valid now and matches its private key."""
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives import serialization
    from cryptography.x509.oid import NameOID

    try:
        ca = x509.load_pem_x509_certificate(identity.ca_pem.encode())
        cert = x509.load_pem_x509_certificate(identity.cert_pem.encode())
        key = serialization.load_pem_private_key(identity.key_pem.get_secret_value().encode(), password=None)
    except ValueError as exc:
        raise IdentityError(f"{where}: unreadable certificate or key ({str(exc).splitlines()[0]})") from None
    names = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if names[:1] != [identity.name]:
        raise IdentityError(f"{where}: the certificate names {names[:1] or 'no one'}, not {identity.name!r}")
    try:
        cert.verify_directly_issued_by(ca)
    except (InvalidSignature, ValueError, TypeError) as exc:  # another issuer, or another key type
        raise IdentityError(f"{where}: the certificate of {identity.name!r} is not signed by the bundle's CA "
                            f"({type(exc).__name__})") from None
    now = now or datetime.datetime.now(datetime.timezone.utc)
    if now > cert.not_valid_after_utc:
        raise IdentityError(f"{where}: the certificate of {identity.name!r} expired on "
                            f"{cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC; ask for a new bundle (twohr keys add)")
    if now < cert.not_valid_before_utc:
        raise IdentityError(f"{where}: the certificate of {identity.name!r} is valid only from "
                            f"{cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (is this host's clock right?)")
    public = serialization.PublicFormat.SubjectPublicKeyInfo
    if key.public_key().public_bytes(serialization.Encoding.PEM, public) != \
            cert.public_key().public_bytes(serialization.Encoding.PEM, public):
        raise IdentityError(f"{where}: the private key does not belong to the certificate of {identity.name!r}")


def _common_name(cert_pem: str, where: Path) -> str:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        names = x509.load_pem_x509_certificate(cert_pem.encode()).subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    except ValueError as exc:
        raise IdentityError(f"{where}: unreadable certificate ({str(exc).splitlines()[0]})") from None
    if not names:
        raise IdentityError(f"{where}: the certificate names no one")
    return str(names[0].value)


def env_identity() -> Identity | None:
    """The identity named by ``TWOHR_ZENOH_KEYS`` (a key folder or a bundle), or None."""
    where = os.environ.get("TWOHR_ZENOH_KEYS")
    return load_identity(where) if where else None


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise IdentityError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
