"""``rse certs``: a certificate authority and one TLS identity per process (``cryptography``).

::

    write_certs("certs", ["router", "plant", "monitor", "agent-1", "agent-2"], hosts=["10.0.0.5"])
    # certs/ca.pem, certs/router.pem + router.key, certs/plant.pem + plant.key, ...

Every certificate is signed by one fresh CA (ECDSA P-256, SHA-256). A process's
certificate has its identity as common name (what the router's access control matches,
see :mod:`transport.secure`) and is valid for both ends of a link (server and client
authentication). Its subject alternative names are what a client may call the router:
the given hosts, ``localhost``, ``127.0.0.1``, ``::1`` and the identity itself (``router``,
the service name under docker compose). Beside each identity but the router's, an Ed25519
signing key pair ``{identity}.sig.key`` / ``.sig.pub`` (:mod:`transport.signing`). Private keys are PKCS#8 PEM, mode 0600, written
without a window in which another user could read them. The CA's private key is not
kept: to add an identity, write the whole set again (``--force``).
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

from transport.secure import CA_FILE, validate_identity
from transport.signing import write_signing_key

__all__ = ["write_certs", "validate_host", "DEFAULT_HOSTS", "DEFAULT_DAYS"]

DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")
DEFAULT_DAYS = 365
_DNS_RE = re.compile(r"(?=.{1,253}\Z)(?:[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9])?)(?:\.[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9])?)*\.?\Z")


def validate_host(host: str) -> str:
    """Return ``host`` if it is an IP address or a DNS name, else raise ``ValueError``."""
    if not isinstance(host, str):
        raise ValueError(f"invalid host {host!r}: expected a DNS name or an IP address")
    try:
        ipaddress.ip_address(host.strip("[]"))
        return host.strip("[]")
    except ValueError:
        pass
    if not _DNS_RE.match(host):
        raise ValueError(f"invalid host {host!r}: expected a DNS name (e.g. router.example.org) or an IP address")
    return host


def _crypto():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:
        raise ImportError("rse certs needs the cryptography package: "
                          "pip install 'resilient-state-estimation[secure]' (or pip install cryptography)") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` with mode 0600 from the start (replacing any file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.fchmod(fd, 0o600)  # whatever the umask
        os.write(fd, data)
    finally:
        os.close(fd)
    os.replace(tmp, path)


def _write_public(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def write_certs(
    directory: str | Path,
    identities: Iterable[str],
    *,
    hosts: Sequence[str] = (),
    days: int = DEFAULT_DAYS,
    force: bool = False,
) -> list[Path]:
    """Write ``DIR/ca.pem`` and ``DIR/{identity}.pem`` / ``.key`` for each identity.

    Parameters
    ----------
    directory : path
        Created if missing (mode 0700).
    identities : iterable of str
        ``router``, ``plant``, ``monitor``, ``agent-{i}`` (see
        :func:`transport.secure.validate_identity`).
    hosts : sequence of str
        Extra subject alternative names (DNS names or IP addresses) of every certificate,
        e.g. the router's address as the clients name it.
    days : int
        Validity from now (backdated 5 minutes for clock skew).
    force : bool
        Replace the certificates of an existing set (``DIR/ca.pem`` exists); otherwise
        that is an error.

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    ValueError
        A bad identity, host or validity; an existing set without ``force``.
    ImportError
        ``cryptography`` is not installed (the message says how to install it).
    OSError
        The directory cannot be created or written.
    """
    ids = [validate_identity(i) for i in identities]
    if not ids:
        raise ValueError("no identities to write")
    if len(set(ids)) != len(ids):
        raise ValueError("duplicate identities")
    names = list(dict.fromkeys([*(validate_host(h) for h in hosts), *DEFAULT_HOSTS]))
    if type(days) is not int or not 1 <= days <= 36500:
        raise ValueError(f"days must be an int in [1, 36500], got {days!r}")
    x509, hashes, serialization, ec, EKU, NameOID = _crypto()
    d = Path(directory).expanduser()
    if (d / CA_FILE).exists() and not force:
        raise ValueError(f"{d} already holds a certificate set ({CA_FILE}); use --force to replace it")
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    if not os.access(d, os.W_OK | os.X_OK):
        raise PermissionError(13, "Permission denied (not writable)", str(d))

    now = _dt.datetime.now(_dt.UTC)
    start, end = now - _dt.timedelta(minutes=5), now + _dt.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "resilient-state-estimation"),
                         x509.NameAttribute(NameOID.COMMON_NAME, "rse certificate authority")])
    ca_ski = x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key())
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                       data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                       crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
          .add_extension(ca_ski, critical=False)
          .sign(ca_key, hashes.SHA256()))
    pem = serialization.Encoding.PEM
    written = [d / CA_FILE]
    _write_public(d / CA_FILE, ca.public_bytes(pem))
    for ident in ids:
        key = ec.generate_private_key(ec.SECP256R1())
        san: list = []
        for h in [*names, ident]:
            try:
                san.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                san.append(x509.DNSName(h))
        san = list(dict.fromkeys(san))
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "resilient-state-estimation"),
                                         x509.NameAttribute(NameOID.COMMON_NAME, ident)]))
                .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(start).not_valid_after(end)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                             data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                             crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
                .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
                .add_extension(x509.SubjectAlternativeName(san), critical=False)
                .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski), critical=False)
                .sign(ca_key, hashes.SHA256()))
        _write_private(d / f"{ident}.key", key.private_bytes(pem, serialization.PrivateFormat.PKCS8,
                                                              serialization.NoEncryption()))
        _write_public(d / f"{ident}.pem", cert.public_bytes(pem))
        written += [d / f"{ident}.pem", d / f"{ident}.key"]
        if ident != "router":  # the router forwards; it signs nothing
            written += write_signing_key(d, ident)
    return written
