"""The web's HTTPS certificate: the plant's ([web] certificate and key), or one the cell makes and
keeps in var/web/ (self-signed, naming the host by every name and address a browser may use; made
again when missing or within a day of expiring; the key kept 0600)."""

from __future__ import annotations

import datetime
import ipaddress
import os
import socket
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from gwc.errors import ConfigError
from gwc.web.settings import WebSettings

DAYS = 365


def certificate_names(host: str) -> tuple[list[str], list[str]]:
    """The names and addresses the certificate gives: the host's name, localhost, loopback, the host's
    addresses and the listen address (as the OPC UA gateway's does, without importing asyncua)."""
    dns, ips = [socket.gethostname(), "localhost"], ["127.0.0.1", "::1"]
    try:
        ips += socket.gethostbyname_ex(socket.gethostname())[2]
    except OSError:
        pass
    try:
        ips.append(str(ipaddress.ip_address(host)))
    except ValueError:
        dns.append(host)
    ips = [i for i in ips if i not in ("0.0.0.0", "::")]
    return list(dict.fromkeys(dns)), list(dict.fromkeys(ips))


def _fits(cert_file: Path, dns: list[str], ips: list[str]) -> bool:
    try:
        cert = x509.load_pem_x509_certificate(cert_file.read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except (OSError, ValueError, x509.ExtensionNotFound):
        return False
    if cert.not_valid_after_utc < datetime.datetime.now(datetime.UTC) + datetime.timedelta(days=1):
        return False
    have_ips = {str(i) for i in san.get_values_for_type(x509.IPAddress)}
    return set(dns) <= set(san.get_values_for_type(x509.DNSName)) and set(ips) <= have_ips


def certificate(settings: WebSettings, cell_name: str) -> tuple[Path, Path]:
    """(certificate, key) PEM files for the HTTPS server."""
    if settings.certificate is not None and settings.key is not None:
        for p in (settings.certificate, settings.key):
            if not p.is_file():
                raise ConfigError(f"[web] {p}: no such file")
        return settings.certificate, settings.key
    d = settings.cert_dir
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    cert_file, key_file = d / "cert.pem", d / "key.pem"
    dns, ips = certificate_names(settings.host)
    if key_file.is_file() and _fits(cert_file, dns, ips):
        return cert_file, key_file
    if key_file.is_file():
        key = serialization.load_pem_private_key(key_file.read_bytes(), None)
        assert isinstance(key, ec.EllipticCurvePrivateKey)
    else:
        key = ec.generate_private_key(ec.SECP256R1())
        fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(
                key.private_bytes(
                    serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
                )
            )
    name = x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "GWC"),
            x509.NameAttribute(NameOID.COMMON_NAME, f"GWC web HMI {cell_name}"),
        ]
    )
    now = datetime.datetime.now(datetime.UTC)
    san = [x509.DNSName(n) for n in dns] + [x509.IPAddress(ipaddress.ip_address(i)) for i in ips]
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=DAYS))
        .add_extension(x509.SubjectAlternativeName(san), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .sign(key, hashes.SHA256())
    )
    cert_file.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert_file, key_file
