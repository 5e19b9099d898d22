"""The plant gateway's OPC UA credentials, made with the Zenoh logins by `machine credentials init`.

- `gateway-opcua.der` + `gateway-opcua.key.pem`: a self-signed application instance certificate
  (RSA 2048, SHA-256, as the Basic256Sha256 policy asks) whose subject alternative name carries
  the gateway's application URI and the host names it serves, for the Sign & Encrypt endpoint;
- `opcua-users`: the OPC UA operators, one `user:password` line (a random password for
  `operator`), for `rider gateway --users`.
A SCADA trusts the certificate once (UaExpert: "Trust server certificate"), docs/plant.md.
"""

from __future__ import annotations

import datetime
import ipaddress
import secrets
import socket
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from ride_machine.service.core.storage.atomic import NewFile, write_together

APPLICATION_URI = "urn:ride-machine:gateway"
"""The gateway's OPC UA application URI (rider/gateway/server.py); its certificate names it."""
CERTIFICATE = "gateway-opcua.der"
PRIVATE_KEY = "gateway-opcua.key.pem"
USERS = "opcua-users"
OPERATOR = "operator"
VALID_DAYS = 825
PASSWORD_BYTES = 24


def opcua_files(directory: Path) -> list[Path]:
    return [directory / CERTIFICATE, directory / PRIVATE_KEY, directory / USERS]


def init_opcua(directory: Path, hosts: tuple[str, ...] = ()) -> list[Path]:
    """Write the certificate, its key (0600) and the operators file, together or none; the
    paths written. The caller checked that they may be (re)written."""
    files = opcua_new_files(directory, hosts)
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    write_together(files)
    return [f.path for f in files]


def opcua_new_files(directory: Path, hosts: tuple[str, ...] = ()) -> list[NewFile]:
    """A fresh certificate, its key and an operator password, as files to write (with the
    machine's credentials, `init_credentials(also=…)`: all of them or none)."""
    names = ("localhost", socket.gethostname(), *hosts)
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    cert = _certificate(key, names)
    cert_path, key_path, users_path = opcua_files(directory)
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    password = secrets.token_urlsafe(PASSWORD_BYTES)
    return [
        NewFile(cert_path, cert.public_bytes(serialization.Encoding.DER), 0o644),
        NewFile(key_path, pem, 0o600),
        NewFile(users_path, f"{OPERATOR}:{password}\n".encode(), 0o600),
    ]


def _certificate(key: rsa.RSAPrivateKey, names: tuple[str, ...]) -> x509.Certificate:
    subject = x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, "ride-machine gateway"),
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "ride-machine"),
        ]
    )
    alt: list[x509.GeneralName] = [x509.UniformResourceIdentifier(APPLICATION_URI)]
    alt += [x509.DNSName(n) for n in dict.fromkeys(names) if n]
    alt.append(x509.IPAddress(ipaddress.ip_address("127.0.0.1")))
    now = datetime.datetime.now(datetime.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=True,
                key_encipherment=True,
                data_encipherment=True,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
