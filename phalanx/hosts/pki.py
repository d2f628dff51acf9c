"""A fleet's certificates: a certificate authority and one key and certificate per identity.

Every identity's role is in its certificate's common name, which is what Zenoh's access
control matches and what a host daemon checks on a request (`phalanx.hosts.access`):

    robot.<id>        a robot's agent (it may publish only under its own robot's keys)
    host.<name>       a host's daemon (a Zenoh router: its links to the other hosts)
    operator.<name>   a person who may start and stop a fleet (`phalanx launch`, `stop`)
    viewer.<name>     a person or tool that may only read (`phalanx status`, a viewer)
    world             the simulated world (sense frames, ground truth)

A PKI folder holds `ca.crt` (and `ca.key`, which should not leave the machine that
issues), and `<common name>.crt` / `<common name>.key` for each identity. Keys are ECDSA
P-256, written with mode 0600. A host's certificate names its addresses (and loopback)
as subject alternative names: TLS verifies the name a connection was opened to.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from phalanx.core.errors import ConfigError
from phalanx.core.files import write_private

if TYPE_CHECKING:
    from cryptography import x509

Role = Literal["robot", "host", "operator", "viewer", "world"]
ROLES: tuple[Role, ...] = ("robot", "host", "operator", "viewer", "world")
CA_NAME = "ca"
_COMMON_NAME = re.compile(r"^(robot|host|operator|viewer)\.[A-Za-z0-9_-]{1,64}$|^world$")
MAX_DAYS = 3650


def common_name(role: Role, name: str = "") -> str:
    """`<role>.<name>` (`world` alone); ConfigError for a name outside `[A-Za-z0-9_-]`."""
    cn = "world" if role == "world" else f"{role}.{name}"
    if not _COMMON_NAME.match(cn):
        raise ConfigError(
            f"identity {cn!r}: expected robot.ID, host.NAME, operator.NAME, viewer.NAME or "
            "world, with 1-64 letters, digits, '_' or '-' after the dot"
        )
    return cn


def role_of(cn: str) -> str:
    """The role part of a common name (`robot` of `robot.r1`)."""
    return cn.split(".", 1)[0]


@dataclass(frozen=True)
class Issued:
    """A certificate in a PKI folder, as `phalanx pki list` shows it."""

    common_name: str
    path: Path
    not_before: dt.datetime
    not_after: dt.datetime
    names: tuple[str, ...]  # subject alternative names
    issuer: str

    def expired(self, now: dt.datetime | None = None) -> bool:
        """Whether it is outside its validity period now."""
        now = now or dt.datetime.now(dt.UTC)
        return not self.not_before <= now <= self.not_after


def _key_pem(key: object) -> bytes:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    assert isinstance(key, ec.EllipticCurvePrivateKey)  # noqa: S101 - ours
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _validity(days: float, start: dt.datetime | None) -> tuple[dt.datetime, dt.datetime]:
    if not 0 < days <= MAX_DAYS:
        raise ConfigError(f"validity of {days} days: expected more than 0 and at most {MAX_DAYS}")
    begin = start or dt.datetime.now(dt.UTC) - dt.timedelta(minutes=5)  # clock skew
    return begin, begin + dt.timedelta(days=days)


def init_ca(folder: Path, *, fleet: str, days: float = MAX_DAYS, force: bool = False) -> Path:
    """Create the fleet's certificate authority in `folder`; the path of `ca.crt`.

    Refuses to replace an existing CA unless `force` (every certificate it signed would
    stop working).
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    crt = folder / f"{CA_NAME}.crt"
    if crt.exists() and not force:
        raise ConfigError(f"{crt} exists: a new CA would invalidate every certificate it signed")
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"phalanx fleet CA {fleet}")])
    begin, end = _validity(days, None)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(begin)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_ca_usage(), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
        .sign(key, hashes.SHA256())
    )
    write_private(folder / f"{CA_NAME}.key", _key_pem(key))
    crt.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return crt


def _ca_usage() -> x509.KeyUsage:
    from cryptography import x509

    flags = dict.fromkeys(
        ("content_commitment", "key_encipherment", "data_encipherment", "key_agreement"), False
    )
    return x509.KeyUsage(
        digital_signature=True, key_cert_sign=True, crl_sign=True,
        encipher_only=False, decipher_only=False, **flags,
    )  # fmt: skip


def _load_ca(folder: Path) -> tuple[object, object]:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    crt, key = folder / f"{CA_NAME}.crt", folder / f"{CA_NAME}.key"
    if not crt.is_file() or not key.is_file():
        raise ConfigError(f"{folder}: no CA here (ca.crt and ca.key): run `phalanx pki init` first")
    return (
        x509.load_pem_x509_certificate(crt.read_bytes()),
        serialization.load_pem_private_key(key.read_bytes(), password=None),
    )


def issue(
    folder: Path,
    cn: str,
    *,
    days: float = 365.0,
    addresses: tuple[str, ...] = (),
    start: dt.datetime | None = None,
) -> tuple[Path, Path]:
    """Issue (or re-issue) a key and certificate for `cn`, signed by the CA in `folder`.

    `addresses` (IP addresses or DNS names) go into the subject alternative names; a
    host's certificate always names 127.0.0.1 and localhost as well (its own processes
    reach it there). `start` backdates or postdates the validity (tests make expired
    ones). Returns the certificate's and the key's paths.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not _COMMON_NAME.match(cn):
        raise ConfigError(
            f"identity {cn!r}: expected robot.ID, host.NAME, operator.NAME, viewer.NAME or world"
        )
    ca_cert, ca_key = _load_ca(folder)
    assert isinstance(ca_cert, x509.Certificate)  # noqa: S101 - loaded above
    assert isinstance(ca_key, ec.EllipticCurvePrivateKey)  # noqa: S101
    key = ec.generate_private_key(ec.SECP256R1())
    begin, end = _validity(days, start)
    names = _alt_names(cn, addresses)
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(begin)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
        )
        .sign(ca_key, hashes.SHA256())
    )
    crt_path, key_path = folder / f"{cn}.crt", folder / f"{cn}.key"
    write_private(key_path, _key_pem(key))
    crt_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return crt_path, key_path


def _alt_names(cn: str, addresses: tuple[str, ...]) -> list[x509.GeneralName]:
    from cryptography import x509

    wanted = list(addresses)
    if role_of(cn) == "host":
        wanted += ["127.0.0.1", "localhost"]
    names: list[x509.GeneralName] = [x509.DNSName(cn)]
    for value in dict.fromkeys(wanted):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(value)))
        except ValueError:
            names.append(x509.DNSName(value))
    return names


def read_issued(path: Path) -> Issued:
    """What the certificate at `path` says (ConfigError if it is not one)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        cert = x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: not a PEM certificate ({exc})") from exc
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    issuer = cert.issuer.get_attributes_for_oid(NameOID.COMMON_NAME)
    try:
        alt = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        names = tuple(str(n.value) for n in alt)
    except x509.ExtensionNotFound:
        names = ()
    return Issued(
        common_name=str(cns[0].value) if cns else "",
        path=path,
        not_before=cert.not_valid_before_utc,
        not_after=cert.not_valid_after_utc,
        names=names,
        issuer=str(issuer[0].value) if issuer else "",
    )


def list_issued(folder: Path) -> list[Issued]:
    """Every certificate in `folder` (the CA first), oldest expiry first after it."""
    if not folder.is_dir():
        raise ConfigError(f"{folder}: no such PKI folder")
    found = [read_issued(p) for p in sorted(folder.glob("*.crt"))]
    found.sort(key=lambda i: (i.path.stem != CA_NAME, i.not_after))
    return found


def verify_chain(cert_pem: bytes, ca_path: Path, *, now: dt.datetime | None = None) -> str:
    """The common name of `cert_pem` if the CA at `ca_path` signed it and it is valid now;
    ConfigError saying why not otherwise.
    """
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
    try:
        cert = x509.load_pem_x509_certificate(cert_pem)
    except ValueError as exc:
        raise ConfigError(f"not a PEM certificate: {exc}") from exc
    public = ca.public_key()
    assert isinstance(public, ec.EllipticCurvePublicKey)  # noqa: S101 - our CAs are ECDSA
    try:
        public.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(hashes.SHA256()))
    except InvalidSignature as exc:
        raise ConfigError("certificate not signed by this fleet's CA") from exc
    if cert.issuer != ca.subject:
        raise ConfigError("certificate issued by another CA")
    now = now or dt.datetime.now(dt.UTC)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        raise ConfigError(f"certificate outside its validity (until {cert.not_valid_after_utc})")
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(cns[0].value) if cns else ""
