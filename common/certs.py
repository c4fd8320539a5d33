"""A development certificate authority for the zenoh mTLS setup (`dynqos certs`).

Zenoh's access control matches a remote's certificate common name, so each drone gets a certificate
whose CN is its drone id, the edge services share one with CN `edge`, and the router has one whose
subject alternative names cover the names drones dial. For production, use your own PKI; this is the
same layout made in one command so that the secure configs can be tried (and tested) locally.
Uses `cryptography` rather than shelling out to openssl: no external binary, errors as exceptions.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dynqos.common.errors import DynqosError
from dynqos.common.keys import check_uav_id

EDGE_COMMON_NAME = "edge"
ROUTER_COMMON_NAME = "router"


@dataclass(frozen=True, slots=True)
class Issued:
    cert: Path
    key: Path


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dynqos"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)  # private keys: owner only
    with os.fdopen(fd, "wb") as out:
        out.write(data)


def _san(name: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


class DevCa:
    """A CA in `folder` (ca.pem, ca-key.pem), created on first use, that issues leaf certificates."""

    def __init__(self, folder: Path, *, days: int = 365) -> None:
        if not 1 <= days <= 3650:
            raise DynqosError(f"certificate validity must be 1..3650 days, got {days}")
        self.folder = folder
        self.days = days
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DynqosError(f"cannot create {folder}: {exc.strerror}") from None
        self.cert_path, self.key_path = folder / "ca.pem", folder / "ca-key.pem"
        if self.cert_path.exists() and self.key_path.exists():
            self.cert = x509.load_pem_x509_certificate(self.cert_path.read_bytes())
            key = serialization.load_pem_private_key(self.key_path.read_bytes(), password=None)
            if not isinstance(key, ec.EllipticCurvePrivateKey):
                raise DynqosError(f"{self.key_path}: not an EC private key made by dynqos certs")
            self.key = key
        else:
            self.key = ec.generate_private_key(ec.SECP256R1())
            now = dt.datetime.now(dt.timezone.utc)
            self.cert = (
                x509.CertificateBuilder()
                .subject_name(_name("dynqos dev CA"))
                .issuer_name(_name("dynqos dev CA"))
                .public_key(self.key.public_key())
                .serial_number(x509.random_serial_number())
                .not_valid_before(now - dt.timedelta(minutes=5))
                .not_valid_after(now + dt.timedelta(days=self.days))
                .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                .add_extension(
                    x509.KeyUsage(
                        digital_signature=False,
                        content_commitment=False,
                        key_encipherment=False,
                        data_encipherment=False,
                        key_agreement=False,
                        key_cert_sign=True,
                        crl_sign=True,
                        encipher_only=False,
                        decipher_only=False,
                    ),
                    critical=True,
                )
                .sign(self.key, hashes.SHA256())
            )
            _write_key(self.key_path, self.key)
            self.cert_path.write_bytes(self.cert.public_bytes(serialization.Encoding.PEM))

    def issue(self, common_name: str, *, hosts: tuple[str, ...] = (), server: bool = False) -> Issued:
        """A key and certificate `<cn>.pem` / `<cn>-key.pem`, for TLS client auth (and server auth)."""
        key = ec.generate_private_key(ec.SECP256R1())
        now = dt.datetime.now(dt.timezone.utc)
        usages = [ExtendedKeyUsageOID.CLIENT_AUTH] + ([ExtendedKeyUsageOID.SERVER_AUTH] if server else [])
        names = hosts or (common_name,)
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(common_name))
            .issuer_name(self.cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=self.days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
            .add_extension(x509.SubjectAlternativeName([_san(n) for n in names]), critical=False)
            .sign(self.key, hashes.SHA256())
        )
        issued = Issued(self.folder / f"{common_name}.pem", self.folder / f"{common_name}-key.pem")
        _write_key(issued.key, key)
        issued.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        return issued


def make_dev_pki(
    folder: Path, drones: list[str], router_hosts: list[str], *, days: int = 365
) -> dict[str, Issued]:
    """CA, router, edge and one certificate per drone id in `folder`; returns them by common name."""
    for uav in drones:
        check_uav_id(uav)
    if EDGE_COMMON_NAME in drones or ROUTER_COMMON_NAME in drones:
        raise DynqosError(f"drone ids {EDGE_COMMON_NAME!r} and {ROUTER_COMMON_NAME!r} are reserved")
    ca = DevCa(folder, days=days)
    hosts = tuple(dict.fromkeys(["localhost", "127.0.0.1", *router_hosts]))
    issued = {ROUTER_COMMON_NAME: ca.issue(ROUTER_COMMON_NAME, hosts=hosts, server=True)}
    issued[EDGE_COMMON_NAME] = ca.issue(EDGE_COMMON_NAME)
    for uav in drones:
        issued[uav] = ca.issue(uav)
    return issued
