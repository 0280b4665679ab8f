"""X.509 for a fleet: its certificate authority, and certificates of that CA for services and robots.

``cryptography`` does every cryptographic step (EC P-256 keys, X.509 v3 certificates signed with SHA-256). It is
imported inside each function, so that a plain ``twohr up`` never loads it.
"""

from __future__ import annotations

import datetime
import ipaddress
import os

#: Certificates start a little in the past, so that a host whose clock is a little behind accepts them.
CLOCK_SKEW = datetime.timedelta(minutes=5)


def _start(not_before: datetime.datetime | None = None) -> datetime.datetime:
    return not_before or datetime.datetime.now(datetime.timezone.utc) - CLOCK_SKEW


def pem(obj) -> str:
    """A certificate, or a private key (PKCS#8, unencrypted), as PEM text."""
    from cryptography.hazmat.primitives import serialization

    if hasattr(obj, "public_bytes"):
        return obj.public_bytes(serialization.Encoding.PEM).decode()
    return obj.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption()).decode()


def make_ca(days: float):
    """A new fleet CA: a self-signed certificate that may sign end certificates only; returns ``(cert, key)``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    # not a secret: a random serial tells one fleet's CA name from another's
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "twohr fleet CA"),
                      x509.NameAttribute(NameOID.SERIAL_NUMBER, os.urandom(8).hex())])
    start = _start()
    usage = x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False, encipher_only=False,
                          decipher_only=False)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(start)
            .not_valid_after(start + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(usage, critical=True)
            .sign(key, hashes.SHA256()))
    return cert, key


def load_ca(cert_pem: bytes, key_pem: bytes):
    """The CA's ``(cert, key)`` from their PEM files' bytes."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    return x509.load_pem_x509_certificate(cert_pem), serialization.load_pem_private_key(key_pem, password=None)


def issue(ca, ca_key, name: str, days: float, hosts: list[str] | None = None,
          not_before: datetime.datetime | None = None):
    """A new key and a certificate of ``ca`` for common name ``name`` (client and server use; ``hosts`` as
    subject alternative names); returns ``(cert, key)``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    start = _start(not_before)
    # valid ``days`` from now (or from ``not_before``): a short-lived certificate's lifetime is not eaten by the skew
    until = (not_before or datetime.datetime.now(datetime.timezone.utc)) + datetime.timedelta(days=days)
    builder = (x509.CertificateBuilder()
               .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
               .issuer_name(ca.subject).public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(start).not_valid_after(until)
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH,
                                                     ExtendedKeyUsageOID.SERVER_AUTH]), critical=False))
    if hosts:
        builder = builder.add_extension(alt_names(hosts), critical=False)
    return builder.sign(ca_key, hashes.SHA256()), key


def alt_names(hosts: list[str]):
    """Subject alternative names: an IP address for each host that is one, a DNS name for the others."""
    from cryptography import x509

    names = []
    for host in dict.fromkeys(hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host.strip("[]"))))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def served_hosts(cert_pem: bytes) -> list[str]:
    """The host names and addresses a certificate names."""
    from cryptography import x509

    cert = x509.load_pem_x509_certificate(cert_pem)
    try:
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    return [str(n) for n in names.get_values_for_type(x509.DNSName)] + [
        str(n) for n in names.get_values_for_type(x509.IPAddress)]
