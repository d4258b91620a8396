"""TLS identities of a deployment (``python -m swarm deploy``): a fresh CA and, for each name,
a certificate it signs, made with ``cryptography`` (the ``[deploy]`` extra).

Importing this module without the extra raises :class:`protocol.distribution.MissingExtra`;
:func:`swarm.deploy.write_deployment` imports it before it writes anything. ``swarm run``
needs none of it: its embedded router admits users by random passwords only.
"""
from __future__ import annotations

import datetime
import ipaddress
from dataclasses import dataclass

from protocol.distribution import needs

with needs("deploy"):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CERT_DAYS = 365
CA_NAME = "koopman-swarm deployment CA"
ROUTER_NAME = "router"  # the common name of the router's certificate


@dataclass(frozen=True)
class Identity:
    """One name's TLS files, PEM-encoded: the CA's certificate, its own, and its private key."""

    ca: bytes
    cert: bytes
    key: bytes


def _certificate(name: str, public_key, issuer_name, signing_key, *, ca: bool,
                 hosts: tuple[str, ...] = ()) -> x509.Certificate:
    """An X.509 certificate for ``name`` (ECDSA P-256 with SHA-256), valid CERT_DAYS days."""
    now = datetime.datetime.now(datetime.UTC)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    builder = (x509.CertificateBuilder()
               .subject_name(subject)
               .issuer_name(subject if issuer_name is None else issuer_name)
               .public_key(public_key)
               .serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=CERT_DAYS))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None),
                              critical=True))
    if ca:
        builder = builder.add_extension(x509.KeyUsage(
            digital_signature=False, content_commitment=False, key_encipherment=False,
            data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
            encipher_only=False, decipher_only=False), critical=True)
    else:
        builder = builder.add_extension(x509.KeyUsage(
            digital_signature=True, content_commitment=False, key_encipherment=False,
            data_encipherment=False, key_agreement=True, key_cert_sign=False, crl_sign=False,
            encipher_only=False, decipher_only=False), critical=True)
        builder = builder.add_extension(x509.ExtendedKeyUsage(
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        alt_names = []
        for host in hosts:
            try:
                alt_names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                alt_names.append(x509.DNSName(host))
        builder = builder.add_extension(x509.SubjectAlternativeName(
            alt_names or [x509.DNSName(name)]), critical=False)
    return builder.sign(signing_key, hashes.SHA256())


def identities(names: list[str], router_hosts: tuple[str, ...]
               ) -> tuple[Identity, dict[str, Identity]]:
    """A fresh CA; the router's identity, valid for ``router_hosts``, and one for each of
    ``names`` (a user, named in its certificate's common name). The CA's private key is
    discarded, so no further certificate can be signed with it."""
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_cert = _certificate(CA_NAME, ca_key.public_key(), None, ca_key, ca=True)
    ca_pem = ca_cert.public_bytes(serialization.Encoding.PEM)

    def identity(name: str, hosts: tuple[str, ...] = ()) -> Identity:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _certificate(name, key.public_key(), ca_cert.subject, ca_key, ca=False,
                            hosts=hosts)
        return Identity(ca_pem, cert.public_bytes(serialization.Encoding.PEM),
                        key.private_bytes(serialization.Encoding.PEM,
                                          serialization.PrivateFormat.PKCS8,
                                          serialization.NoEncryption()))

    return identity(ROUTER_NAME, router_hosts), {name: identity(name) for name in names}
