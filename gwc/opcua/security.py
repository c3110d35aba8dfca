"""Who may do what on the gateway (docs/opcua.md, Security).

* Anonymous sessions (when [opcua] anonymous is true) browse, read and subscribe; they may ask for
  ConditionRefresh (the active alarms again) but call nothing else.
* A user (a name and password from [opcua] users, or a certificate of [opcua] user_certificates)
  may also call methods, but only over a SignAndEncrypt channel: a password sent over an unsecured
  channel must not be enough to stop a machine. A password sent unencrypted over an unsecured
  channel is refused outright; passwords are kept as salted scrypt hashes, never in clear.

asyncua hands every secure channel the permission ruleset of the endpoint it opened, but one
ruleset object is shared by all endpoints; `GatewayServer` gives each endpoint its own, so the rule
can know whether the channel is encrypted.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import logging
import os
import socket
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import Buffer
from asyncua.crypto import uacrypto
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.ua.ua_binary import struct_from_binary
from cryptography.x509.oid import ExtendedKeyUsageOID

from gwc.errors import ConfigError
from gwc.opcua.settings import OpcuaSettings, parse_hash

CALL = ua.NodeId(ua.Int32(ua.ObjectIds.CallRequest_Encoding_DefaultBinary))
WRITE = ua.NodeId(ua.Int32(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary))
# Calls anyone who may subscribe may make: the standard "send me the active alarms again".
REFRESH = {
    ua.NodeId(ua.Int32(ua.ObjectIds.ConditionType_ConditionRefresh)),
    ua.NodeId(ua.Int32(ua.ObjectIds.ConditionType_ConditionRefresh2)),
}
SECURE_POLICIES = [
    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    ua.SecurityPolicyType.Aes256Sha256RsaPss_SignAndEncrypt,
]
OPERATOR = "operator"  # the role name a method's caller gets


# Passwords are kept as salted scrypt hashes ("scrypt$N$r$p$salt$hash", base64): slow to try by the
# million, so cell.toml leaking gives no password away (docs/opcua.md; `gwc key opcua-password`).
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1  # about 16 MiB and tens of milliseconds a try


class ClearText(str):
    """A password a client sent unencrypted (no EncryptionAlgorithm): on an unsecured channel it
    crossed the network readable, and is refused (GatewayUsers.get_user)."""


def hash_password(password: str, salt: bytes | None = None) -> str:
    """The form [opcua] users keeps a password in."""
    salt = os.urandom(16) if salt is None else salt
    digest = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, dklen=32)
    b64 = base64.b64encode
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${b64(salt).decode()}${b64(digest).decode()}"


def password_matches(stored: str, given: str) -> bool:
    """A configured salted hash (parse_hash) against the password a client gave."""
    try:
        n, r, p, salt, digest = parse_hash(stored)
    except ValueError:
        return False
    tried = hashlib.scrypt(given.encode(), salt=salt, n=n, r=r, p=p, dklen=len(digest), maxmem=2**31 - 1)
    return hmac.compare_digest(tried, digest)


class GatewayUsers:
    """asyncua's user manager: anonymous (if allowed), a configured password, or a configured certificate."""

    def __init__(self, settings: OpcuaSettings, log: logging.Logger) -> None:
        self.settings = settings
        self.log = log
        self.certificates: dict[bytes, str] = {}

    async def load(self) -> None:
        for name, path in self.settings.user_certificates.items():
            try:
                cert = await uacrypto.load_certificate(path, "pem" if path.suffix == ".pem" else "der")
            except (OSError, ValueError) as e:
                raise ConfigError(f"[opcua] user_certificates {name}: cannot read {path}: {e}") from None
            self.certificates[uacrypto.der_from_x509(cert)] = name

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> User | None:
        """asyncua passes the channel's client certificate with every token, not only with a certificate
        token: a certificate that is not configured makes no user, and the session is anonymous."""
        if username is not None:
            if isinstance(password, ClearText) and certificate is None:  # no client certificate: the None channel
                self.log.warning(
                    "OPC UA session refused: %r sent its password unencrypted over an unsecured channel "
                    "(use a SignAndEncrypt endpoint)",
                    username,
                )
                return None
            stored = self.settings.users.get(username)
            if stored is None or not password_matches(stored, password or ""):
                self.log.warning("OPC UA session refused: wrong user name or password for %r", username)
                return None
            return User(role=UserRole.User, name=username)
        if certificate is not None:
            der = certificate if isinstance(certificate, bytes) else uacrypto.der_from_x509(certificate)
            name = self.certificates.get(der)
            if name is not None:
                return User(role=UserRole.User, name=name)
        if not self.settings.anonymous:
            self.log.warning("OPC UA session refused: anonymous, and [opcua] anonymous is false")
            return None
        return User(role=UserRole.Anonymous)


class GatewayRules(PermissionRuleset):
    """One endpoint's rule: reads and subscriptions for every session; calls only for a user on an
    encrypted channel (and ConditionRefresh for anyone); no writes (the address space is read-only)."""

    READ_TYPES = frozenset(ua.NodeId(ua.Int32(t)) for t in USER_TYPES) - {CALL, WRITE}

    def __init__(self, encrypted: bool) -> None:
        self.encrypted = encrypted

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Buffer) -> bool:
        if action_type_id in self.READ_TYPES:
            return True
        if action_type_id != CALL:
            return False
        if self.encrypted and user.role in (UserRole.User, UserRole.Admin):
            return True
        calls = struct_from_binary(ua.CallParameters, body.copy()).MethodsToCall
        return all(c.MethodId in REFRESH for c in calls)


class GatewayServer(Server):
    """asyncua's Server with a rule per endpoint (see the module docstring)."""

    async def _setup_server_nodes(self) -> None:
        await super()._setup_server_nodes()
        for factory in self._policies:
            factory.permission_ruleset = GatewayRules(factory.mode == ua.MessageSecurityMode.SignAndEncrypt)
        decrypt = self.iserver.decrypt_user_token

        def marked(isession: Any, token: ua.UserNameIdentityToken) -> tuple[str, str]:
            """asyncua's decryption, with a password that came unencrypted marked ClearText."""
            name, password = decrypt(isession, token)
            return name, (password if token.EncryptionAlgorithm else ClearText(password or ""))

        self.iserver.decrypt_user_token = marked  # type: ignore[method-assign]


async def server_certificate(settings: OpcuaSettings, app_uri: str) -> tuple[Path, Path]:
    """The server's certificate and key under var/opcua/, made (self-signed) when missing or expired."""
    settings.cert_dir.mkdir(parents=True, exist_ok=True)
    cert, key = settings.cert_dir / "server-cert.der", settings.cert_dir / "server-key.pem"
    await setup_self_signed_certificate(
        key,
        cert,
        app_uri,
        socket.gethostname(),
        [ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH],
        {"organizationName": "GWC", "commonName": "GWC OPC UA gateway"},
    )
    key.chmod(0o600)
    return cert, key


def identity_tokens(settings: OpcuaSettings) -> list[type]:
    tokens: list[type] = [ua.UserNameIdentityToken, ua.X509IdentityToken]
    return ([ua.AnonymousIdentityToken] if settings.anonymous else []) + tokens


def security_policies(settings: OpcuaSettings) -> list[ua.SecurityPolicyType]:
    """An unsecured endpoint only for anonymous browsing; otherwise SignAndEncrypt alone."""
    return ([ua.SecurityPolicyType.NoSecurity] if settings.anonymous else []) + SECURE_POLICIES
