"""A development certificate authority for the zenoh mTLS setup (`dynqos certs`).

Zenoh's access control matches a remote's certificate common name, so each drone gets a certificate
whose CN is its drone id, each edge service one of its own (`edge-mpc`, ...: common/acl.py), and the
router one whose subject alternative names cover the names drones dial. For production, use your own
PKI with the same names; this is that layout in one command, so the secure configs can be tried and
tested locally.

Private keys are the reason for the care here: each file is written through a new temporary file
created 0600 (never through an existing file or a link planted at its path) and renamed into place,
in a folder kept 0700; a key pair that exists is kept unless `force`, so re-running the command to add
a drone does not churn the others; no certificate outlives the CA that signed it.
Uses `cryptography` rather than shelling out to openssl: no external binary, errors as exceptions.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dynqos.common.acl import (
    EDGE_ROLES,
    ROUTER_COMMON_NAME,
    edge_common_name,
    reserved_name,
    task_common_name,
)
from dynqos.common.errors import DynqosError
from dynqos.common.keys import check_uav_id

log = logging.getLogger(__name__)

CA_COMMON_NAME = "dynqos dev CA"
MAX_DAYS = 3650


@dataclass(frozen=True, slots=True)
class Issued:
    cert: Path
    key: Path
    kept: bool = False  # an existing pair, left as it was


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dynqos"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def write_atomically(path: Path, data: bytes, mode: int) -> None:
    """Write `data` to `path` with `mode`, atomically: a fresh temporary file beside it, created with
    `mode` (so a private key is never readable by others, not even for a moment), then renamed over
    `path`. A symlink at `path` is replaced, not followed."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as out:
            out.write(data)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _key_bytes(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _san(name: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def _private_folder(folder: Path) -> None:
    """`folder` exists, is a real directory (not a link) and is 0700."""
    if folder.is_symlink():
        raise DynqosError(f"{folder} is a symbolic link: give the real folder for private keys")
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        if stat.S_IMODE(folder.stat().st_mode) != 0o700:
            log.warning("certs: %s was readable by others; made it 0700", folder)
            folder.chmod(0o700)
    except OSError as exc:
        raise DynqosError(f"cannot create {folder}: {exc.strerror}") from None


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


class DevCa:
    """A CA in `folder` (ca.pem, ca-key.pem), created on first use, that issues leaf certificates."""

    def __init__(self, folder: Path, *, ca_days: int = 1825) -> None:
        if not 1 <= ca_days <= MAX_DAYS:
            raise DynqosError(f"CA validity must be 1..{MAX_DAYS} days, got {ca_days}")
        self.folder = folder
        _private_folder(folder)
        self.cert_path, self.key_path = folder / "ca.pem", folder / "ca-key.pem"
        if self.cert_path.exists() and self.key_path.exists():
            self._load()
        else:
            self._create(ca_days)

    def _load(self) -> None:
        self.cert = x509.load_pem_x509_certificate(self.cert_path.read_bytes())
        key = serialization.load_pem_private_key(self.key_path.read_bytes(), password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise DynqosError(f"{self.key_path}: not an EC private key made by dynqos certs")
        self.key = key
        if self.cert.not_valid_after_utc <= _now():
            raise DynqosError(
                f"{self.cert_path} expired on {self.cert.not_valid_after_utc:%Y-%m-%d}: make a new CA in a "
                "new folder and issue every certificate again (docs/security.md, rotation)"
            )

    def _create(self, days: int) -> None:
        self.key = ec.generate_private_key(ec.SECP256R1())
        now = _now()
        self.cert = (
            x509.CertificateBuilder()
            .subject_name(_name(CA_COMMON_NAME))
            .issuer_name(_name(CA_COMMON_NAME))
            .public_key(self.key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days))
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
        write_atomically(self.key_path, _key_bytes(self.key), 0o600)
        write_atomically(self.cert_path, self.cert.public_bytes(serialization.Encoding.PEM), 0o644)

    def pair(self, common_name: str) -> Issued:
        return Issued(self.folder / f"{common_name}.pem", self.folder / f"{common_name}-key.pem")

    def still_good(self, issued: Issued) -> bool:
        """An existing pair this CA signed, not expired, whose key matches its certificate."""
        try:
            cert = x509.load_pem_x509_certificate(issued.cert.read_bytes())
            key = serialization.load_pem_private_key(issued.key.read_bytes(), password=None)
            cert.verify_directly_issued_by(self.cert)
        except (OSError, ValueError, TypeError, InvalidSignature):
            return False
        return cert.not_valid_after_utc > _now() and cert.public_key() == key.public_key()

    def issue(
        self,
        common_name: str,
        *,
        days: int = 365,
        hosts: tuple[str, ...] = (),
        server: bool = False,
        not_before: dt.datetime | None = None,
    ) -> Issued:
        """A new key and certificate `<cn>.pem` / `<cn>-key.pem` for TLS client auth (and server auth),
        valid for `days` but never past the CA's own end."""
        if not 1 <= days <= MAX_DAYS:
            raise DynqosError(f"certificate validity must be 1..{MAX_DAYS} days, got {days}")
        key = ec.generate_private_key(ec.SECP256R1())
        start = not_before or _now() - dt.timedelta(minutes=5)
        end = min(start + dt.timedelta(days=days), self.cert.not_valid_after_utc)
        if end <= start:
            raise DynqosError(f"the CA ends on {end:%Y-%m-%d}: no room for a certificate starting {start}")
        usages = [ExtendedKeyUsageOID.CLIENT_AUTH] + ([ExtendedKeyUsageOID.SERVER_AUTH] if server else [])
        names = hosts or (common_name,)
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(common_name))
            .issuer_name(self.cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start)
            .not_valid_after(end)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
            .add_extension(x509.SubjectAlternativeName([_san(n) for n in names]), critical=False)
            .sign(self.key, hashes.SHA256())
        )
        issued = self.pair(common_name)
        write_atomically(issued.key, _key_bytes(key), 0o600)
        write_atomically(issued.cert, cert.public_bytes(serialization.Encoding.PEM), 0o644)
        return issued


def make_dev_pki(
    folder: Path,
    drones: list[str],
    router_hosts: list[str],
    *,
    days: int = 365,
    ca_days: int = 1825,
    force: bool = False,
    tasks: list[str] | tuple[str, ...] = (),
) -> dict[str, Issued]:
    """CA, router, one identity per edge service, per user task's service (`tasks`) and per drone id in
    `folder`; returns them by common name. Pairs that exist and are still good are kept unless `force`."""
    for uav in drones:
        check_uav_id(uav)
        if reserved_name(uav):
            raise DynqosError(f"drone id {uav!r} is reserved: router, edge and edge-* name the edge")
    ca = DevCa(folder, ca_days=ca_days)
    hosts = tuple(dict.fromkeys(["localhost", "127.0.0.1", *router_hosts]))
    issued: dict[str, Issued] = {}
    services = [*(edge_common_name(s) for s in EDGE_ROLES), *(task_common_name(t) for t in tasks)]
    for name in [ROUTER_COMMON_NAME, *services, *drones]:
        existing = ca.pair(name)
        router = name == ROUTER_COMMON_NAME
        if not force and ca.still_good(existing) and (not router or _same_hosts(existing, hosts)):
            issued[name] = Issued(existing.cert, existing.key, kept=True)
        else:
            issued[name] = ca.issue(name, days=days, hosts=hosts if router else (), server=router)
    return issued


def _same_hosts(issued: Issued, hosts: tuple[str, ...]) -> bool:
    """The router's certificate already names exactly `hosts` (a new --router-host needs a new one)."""
    cert = x509.load_pem_x509_certificate(issued.cert.read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    have = {str(n.value) for n in names}
    return have == set(hosts)
