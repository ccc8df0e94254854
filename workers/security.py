"""TLS for the Dask comms: a project CA, per-role certificates, and ``Security`` objects.

Every connection between the client, the scheduler and the workers uses ``tls://`` with
mutual certificates when TLS is configured: each side presents a certificate signed by
the project CA and verifies the other's (``ssl.CERT_REQUIRED`` in distributed), so a
client without a certificate from this CA is refused during the handshake.

Certificates live in one directory with fixed names (what :func:`make_certificates`,
``schlieren tls init DIR`` and ``deploy/tls/make-certs.sh`` write)::

    ca.pem                                  the project CA certificate (public)
    ca-key.pem                              the CA private key (keep it off the cluster)
    scheduler.pem  scheduler-key.pem        scheduler certificate and key
    worker.pem     worker-key.pem           worker certificate and key
    client.pem     client-key.pem           client certificate and key

Key files are written with mode 0600.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import logging
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from distributed.security import Security

if TYPE_CHECKING:
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

log = logging.getLogger(__name__)

ROLES = ("scheduler", "worker", "client")
CA_CERT = "ca.pem"
CA_KEY = "ca-key.pem"


def cert_name(role: str) -> str:
    """File name of the certificate of ``role`` inside a TLS directory."""
    _check_role(role)
    return f"{role}.pem"


def key_name(role: str) -> str:
    """File name of the private key of ``role`` inside a TLS directory."""
    _check_role(role)
    return f"{role}-key.pem"


def _check_role(role: str) -> None:
    if role not in ROLES:
        raise ValueError(f"unknown TLS role {role!r}; expected one of {', '.join(ROLES)}")


@dataclass(frozen=True)
class TLSFiles:
    """The three files one party needs for mutual TLS.

    Attributes
    ----------
    ca_file : Path
        PEM certificate of the project CA, used to verify the peer.
    cert : Path
        PEM certificate of this party, signed by the CA.
    key : Path
        PEM private key of ``cert``.
    """

    ca_file: Path
    cert: Path
    key: Path

    @classmethod
    def from_dir(cls, directory: str | os.PathLike[str], role: str = "client") -> TLSFiles:
        """The files of ``role`` inside a directory laid out as by :func:`make_certificates`."""
        d = Path(directory)
        return cls(ca_file=d / CA_CERT, cert=d / cert_name(role), key=d / key_name(role))

    def check(self) -> None:
        """Raise ``FileNotFoundError`` naming the first file that is missing."""
        for label, path in (("CA file", self.ca_file), ("certificate", self.cert), ("key", self.key)):
            if not Path(path).is_file():
                raise FileNotFoundError(f"TLS {label} not found: {path}")


def tls_files_from_config(config: Mapping[str, Any], role: str = "client") -> TLSFiles:
    """Read TLS paths from a config mapping (a section of a YAML file).

    Accepted forms, keys with ``-`` or ``_``::

        {"dir": "/path/to/certs"}                       # a make_certificates directory
        {"ca-file": ..., "cert": ..., "key": ...}        # explicit files

    Relative paths stay relative to the current directory.
    """
    cfg = {str(k).replace("-", "_"): v for k, v in config.items()}
    unknown = set(cfg) - {"dir", "ca_file", "cert", "key"}
    if unknown:
        raise ValueError(f"unknown TLS setting(s): {', '.join(sorted(unknown))}")
    if cfg.get("dir"):
        files = TLSFiles.from_dir(Path(cfg["dir"]).expanduser(), role)
        return TLSFiles(
            ca_file=Path(cfg["ca_file"]).expanduser() if cfg.get("ca_file") else files.ca_file,
            cert=Path(cfg["cert"]).expanduser() if cfg.get("cert") else files.cert,
            key=Path(cfg["key"]).expanduser() if cfg.get("key") else files.key,
        )
    missing = [k for k in ("ca_file", "cert", "key") if not cfg.get(k)]
    if missing:
        raise ValueError(f"TLS config needs 'dir' or all of ca-file, cert, key (missing {', '.join(missing)})")
    return TLSFiles(*(Path(cfg[k]).expanduser() for k in ("ca_file", "cert", "key")))


def make_security(files: TLSFiles, role: str = "client", *, require_encryption: bool = True) -> Security:
    """A ``distributed.security.Security`` for one party (``role``) of the cluster.

    Parameters
    ----------
    files : TLSFiles
        CA, certificate and key of this party.
    role : {"client", "scheduler", "worker"}
        Which slot of ``Security`` the certificate fills.
    require_encryption : bool
        Refuse any non-TLS comm (``tcp://``); default True.
    """
    _check_role(role)
    files.check()
    kwargs = {
        "tls_ca_file": str(files.ca_file),
        f"tls_{role}_cert": str(files.cert),
        f"tls_{role}_key": str(files.key),
    }
    return Security(require_encryption=require_encryption, **kwargs)


def cluster_security(directory: str | os.PathLike[str], *, require_encryption: bool = True,
                     check: bool = True) -> Security:
    """A ``Security`` holding all three roles from a certificate directory.

    This is what an in-process cluster (``LocalCluster`` or a dask-jobqueue cluster, whose
    scheduler runs next to the client) needs: the scheduler, the workers it describes and
    the client all take their own certificate from the same object. ``check=False``
    skips the existence check (to print a job script before the certificates exist).
    """
    d = Path(directory)
    kwargs: dict[str, str] = {"tls_ca_file": str(d / CA_CERT)}
    for role in ROLES:
        files = TLSFiles.from_dir(d, role)
        if check:
            files.check()
        kwargs[f"tls_{role}_cert"] = str(files.cert)
        kwargs[f"tls_{role}_key"] = str(files.key)
    return Security(require_encryption=require_encryption, **kwargs)


@dataclass(frozen=True)
class CertificateSet:
    """Paths written by :func:`make_certificates`."""

    directory: Path
    ca_file: Path
    ca_key: Path

    def files(self, role: str) -> TLSFiles:
        """The CA, certificate and key of ``role``."""
        return TLSFiles.from_dir(self.directory, role)


def make_certificates(
    out_dir: str | os.PathLike[str],
    hosts: Iterable[str] = ("127.0.0.1", "localhost"),
    *,
    days: int = 365,
    common_name: str = "schlieren",
    overwrite: bool = False,
) -> CertificateSet:
    """Create a project CA and scheduler/worker/client certificates signed by it.

    The same as ``deploy/tls/make-certs.sh`` (openssl) but in Python (``cryptography``),
    so tests and ``schlieren tls init`` do not need the openssl binary. Keys are ECDSA
    P-256; certificates are valid for both server and client authentication (workers
    connect to each other), with ``hosts`` as subject alternative names (IP addresses
    become IP SANs, everything else DNS SANs).

    Parameters
    ----------
    out_dir : path
        Directory to write into (created if missing).
    hosts : iterable of str
        Host names and IP addresses the scheduler and workers are reached at.
    days : int
        Validity of every certificate, in days.
    common_name : str
        Prefix of the subjects' common names.
    overwrite : bool
        Replace existing files; otherwise an existing ``ca.pem`` raises ``FileExistsError``.

    Returns
    -------
    CertificateSet
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if (out / CA_CERT).exists() and not overwrite:
        raise FileExistsError(f"{out / CA_CERT} exists; pass overwrite=True to replace the CA")
    hosts = list(dict.fromkeys(hosts))
    if not hosts:
        raise ValueError("at least one host name or IP address is needed for the certificates")
    if days <= 0:
        raise ValueError(f"days must be positive, got {days}")

    now = _dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(minutes=5)
    validity = (now, now + _dt.timedelta(days=days))
    ca_key = _new_key()
    ca_cert = _ca_certificate(ca_key, f"{common_name} project CA", validity)
    _write_key(out / CA_KEY, ca_key)
    _write_cert(out / CA_CERT, ca_cert)
    sans = _subject_alt_names(hosts)
    for role in ROLES:
        key = _new_key()
        cert = _role_certificate(key, f"{common_name}-{role}", sans, ca_key, ca_cert, validity)
        _write_key(out / key_name(role), key)
        _write_cert(out / cert_name(role), cert)
    log.info("wrote a project CA and %s certificates to %s", "/".join(ROLES), out)
    return CertificateSet(directory=out, ca_file=out / CA_CERT, ca_key=out / CA_KEY)


# ----------------------------------------------------------------------------------------
# the pieces of make_certificates (cryptography is imported only when certificates are made)


def _new_key() -> ec.EllipticCurvePrivateKey:
    """A fresh ECDSA P-256 private key."""
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _key_usage(*, ca: bool) -> x509.KeyUsage:
    """Key usage of the CA (signs certificates and CRLs) or of a party (signs, agrees keys)."""
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=not ca,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def _ca_certificate(key: ec.EllipticCurvePrivateKey, subject: str,
                    validity: tuple[_dt.datetime, _dt.datetime]) -> x509.Certificate:
    """The self-signed project CA (``path_length=0``: it signs the parties' certificates only)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)])
    return (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(validity[0])
        .not_valid_after(validity[1])
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )


def _subject_alt_names(hosts: Iterable[str]) -> list[x509.GeneralName]:
    """IP addresses as IP SANs, everything else as DNS SANs."""
    from cryptography import x509

    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    return sans


def _role_certificate(key: ec.EllipticCurvePrivateKey, subject: str, sans: list[x509.GeneralName],
                      ca_key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate,
                      validity: tuple[_dt.datetime, _dt.datetime]) -> x509.Certificate:
    """A scheduler, worker or client certificate signed by the CA, for both server and
    client authentication (workers connect to each other), valid for ``sans``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    ca_ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(validity[0])
        .not_valid_after(validity[1])
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski), critical=False)
        .sign(ca_key, hashes.SHA256())
    )


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    """``key`` as unencrypted PKCS#8 PEM, created with mode 0600 (never readable by others)."""
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.chmod(path, 0o600)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    from cryptography.hazmat.primitives import serialization

    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
