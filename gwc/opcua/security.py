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
import datetime
import hashlib
import hmac
import ipaddress
import logging
import os
import secrets
import socket
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from asyncua import Server, ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto import uacrypto
from asyncua.crypto.cert_gen import dump_private_key_as_pem, generate_private_key, generate_self_signed_app_certificate
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.server import binary_server_asyncio
from asyncua.server.internal_session import InternalSession
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from gwc.errors import ConfigError
from gwc.opcua.settings import OpcuaSettings, parse_hash
from gwc.users import Role

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
PRODUCT_URI = "urn:gwc:opcua-gateway"  # the product (BuildInfo, the application description)


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

    def __init__(self, settings: OpcuaSettings, log: logging.Logger, door: Any = None) -> None:
        self.settings = settings
        self.log = log
        self.certificates: dict[bytes, str] = {}
        self.door = door  # gwc.opcua.door.OpcuaDoor: cell users, their roles, the method rule (docs/users.md)

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
            if stored is not None:  # an [opcua] users entry (an MES's account): every method, as before users
                role = "engineer" if password_matches(stored, password or "") else None
            else:  # a cell user, with their own role
                found = self.door.cell_login(username, password or "") if self.door is not None else None
                role = found.name if found is not None else None
            if role is None:
                self.log.warning("OPC UA session refused: wrong user name or password for %r", username)
                return None
            if self.door is not None:
                self.door.roles[username] = Role[role]
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

    def __init__(self, encrypted: bool, door: Any = None) -> None:
        self.encrypted = encrypted
        self.door = door  # gwc.opcua.door.OpcuaDoor: which role may call which method

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Buffer) -> bool:
        if action_type_id in self.READ_TYPES:
            return True
        if action_type_id != CALL:
            return False
        calls = struct_from_binary(ua.CallParameters, body.copy()).MethodsToCall
        if self.encrypted and user.role in (UserRole.User, UserRole.Admin):
            return self.door is None or bool(self.door.check(user.name, [c.MethodId for c in calls]))
        return all(c.MethodId in REFRESH for c in calls)


REPUBLISH = ua.NodeId(ua.Int32(ua.ObjectIds.RepublishRequest_Encoding_DefaultBinary))
# Services a client may ask for on a channel without a session (Part 4: the rest need one).
SESSIONLESS = {
    ua.NodeId(ua.Int32(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary")))
    for name in (
        "CreateSession",
        "CloseSession",
        "ActivateSession",
        "FindServers",
        "GetEndpoints",
        "RegisterServer",
        "RegisterServer2",
        "CloseSecureChannel",
    )
}


class GatewayProcessor(UaProcessor):
    """asyncua's request processor, answering as Part 4 says where asyncua does not, so that a
    standard client's reconnect after a gateway restart gets data again: a request on a channel
    without a session, or naming another session (a client resends its Publish with its lost
    session's token), answers BadSessionIdInvalid, not BadUserAccessDenied (on which clients give
    up); a Republish of a message the server no longer has BadMessageNotAvailable, not an empty
    Good message (on which node-opcua asks again for ever)."""

    async def _process_message(self, typeid: ua.NodeId, requesthdr: Any, seqhdr: Any, body: Buffer) -> Any:
        if typeid not in SESSIONLESS and (
            self.session is None or requesthdr.AuthenticationToken != self.session.auth_token
        ):
            # No session on this channel, or a request naming another one (a Publish a client resends
            # with its lost session's token while it makes a new session): Part 4 says which.
            raise ServiceError(ua.StatusCodes.BadSessionIdInvalid)
        if typeid == REPUBLISH:
            # asyncua answers a message it no longer has with an empty Good one; a client (node-opcua)
            # then asks again and again and never resumes. Part 4: BadMessageNotAvailable.
            params = struct_from_binary(ua.RepublishParameters, body.copy())
            sub = self.iserver.subscription_service.subscriptions.get(params.SubscriptionId)
            if sub is None:
                raise ServiceError(ua.StatusCodes.BadSubscriptionIdInvalid)
            if params.RetransmitSequenceNumber not in sub._not_acknowledged_results:
                raise ServiceError(ua.StatusCodes.BadMessageNotAvailable)
        return await super()._process_message(typeid, requesthdr, seqhdr, body)


def with_timestamps(params: ua.ReadParameters, values: list[ua.DataValue]) -> list[ua.DataValue]:
    """Part 4 Read: a Value read carries the timestamps TimestampsToReturn asks for. asyncua returns
    what was stored: the cell's variables have both (Space writes them); a value of asyncua's own
    address space (ServerStatus, the nodesets' properties) gets a ServerTimestamp of now."""
    want = params.TimestampsToReturn
    source = want in (ua.TimestampsToReturn.Source, ua.TimestampsToReturn.Both)
    server = want in (ua.TimestampsToReturn.Server, ua.TimestampsToReturn.Both)
    now = datetime.datetime.now(datetime.UTC)
    out = []
    for item, dv in zip(params.NodesToRead, values):
        if item.AttributeId != ua.AttributeIds.Value or dv.StatusCode is None or not dv.StatusCode.is_good():
            out.append(dv)
            continue
        fixed = ua.DataValue(
            dv.Value,
            StatusCode=dv.StatusCode,
            SourceTimestamp=dv.SourceTimestamp if source else None,
            ServerTimestamp=(dv.ServerTimestamp or now) if server else None,  # type: ignore[arg-type]
        )
        if dv.Value is None:  # a null kept absent (space.data_value)
            object.__setattr__(fixed, "Value", None)
        out.append(fixed)
    return out


class GatewayServer(Server):
    """asyncua's Server with a rule per endpoint (see the module docstring), GatewayProcessor, and
    Read's timestamps (with_timestamps)."""

    async def init(self, shelf_file: Path | None = None) -> None:
        # asyncua numbers sessions and their authentication tokens from the same start in every
        # process: a client reconnecting after a restart could present a token the new process has
        # given another session. Each process starts from a random number instead.
        InternalSession._counter = secrets.randbelow(2**30) + 1
        InternalSession._auth_counter = secrets.randbelow(2**30) + 2**30
        await super().init(shelf_file)
        # Subscription ids too (asyncua starts at 78 in every process): a client's TransferSubscriptions
        # after a restart must not name, and take over, another client's new subscription.
        self.iserver.subscription_service._sub_id_counter = secrets.randbelow(2**30) + 2**20
        service = self.iserver.attribute_service
        read = service.read
        service.read = lambda params: with_timestamps(params, read(params))  # type: ignore[method-assign]

    async def _setup_server_nodes(self) -> None:
        await super()._setup_server_nodes()
        door = getattr(self.iserver.user_manager, "door", None)
        for factory in self._policies:
            factory.permission_ruleset = GatewayRules(factory.mode == ua.MessageSecurityMode.SignAndEncrypt, door)
        decrypt = self.iserver.decrypt_user_token

        def marked(isession: Any, token: ua.UserNameIdentityToken) -> tuple[str, str]:
            """asyncua's decryption, with a password that came unencrypted marked ClearText."""
            name, password = decrypt(isession, token)
            return name, (password if token.EncryptionAlgorithm else ClearText(password or ""))

        self.iserver.decrypt_user_token = marked  # type: ignore[method-assign]

    async def stop(self) -> None:
        # Listen no more before the open connections are closed: clients reconnect at once (node-opcua
        # within 0.2 s), and a connection made while asyncua stops holds its stop for seconds.
        listener = getattr(self.bserver, "_server", None)
        if listener is not None:
            listener.close()
        await super().stop()

    async def start(self) -> None:
        # asyncua makes each connection's processor from this module-level name; the gateway is a
        # process of its own, so it is replaced for this process only.
        binary_server_asyncio.UaProcessor = GatewayProcessor  # type: ignore[misc]
        await super().start()


def certificate_names(endpoint: str) -> tuple[list[str], list[str]]:
    """The DNS names and IP addresses the server's certificate names: the host's name, localhost,
    the loopback addresses, the host's addresses, and the endpoint's host (a name or an address)."""
    hostname = socket.gethostname()
    dns, ips = [hostname, "localhost"], ["127.0.0.1", "::1"]
    try:
        ips += socket.gethostbyname_ex(hostname)[2]
    except OSError:
        pass
    host = urlparse(endpoint).hostname or ""
    try:
        ipaddress.ip_address(host)
        ips.append(host)
    except ValueError:
        if host:
            dns.append(host)
    ips = [ip for ip in ips if ip not in ("0.0.0.0", "::")]
    return list(dict.fromkeys(dns)), list(dict.fromkeys(ips))


def _certificate_fits(cert: x509.Certificate, app_uri: str, dns: list[str], ips: list[str]) -> bool:
    if cert.not_valid_after_utc < datetime.datetime.now(datetime.UTC) + datetime.timedelta(days=1):
        return False
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return False
    have_ips = {str(ip) for ip in san.get_values_for_type(x509.IPAddress)}
    return (
        app_uri in san.get_values_for_type(x509.UniformResourceIdentifier)
        and set(dns) <= set(san.get_values_for_type(x509.DNSName))
        and {str(ipaddress.ip_address(ip)) for ip in ips} <= have_ips
    )


async def server_certificate(settings: OpcuaSettings, app_uri: str) -> tuple[Path, Path]:
    """The server's certificate and key under var/opcua/, made (self-signed) when missing, expiring,
    or not naming the host by every name and address a client may use (certificate_names). The key
    is kept, so a client that trusted the certificate sees the same key."""
    settings.cert_dir.mkdir(parents=True, exist_ok=True)
    cert_file, key_file = settings.cert_dir / "server-cert.der", settings.cert_dir / "server-key.pem"
    if key_file.is_file():
        key = await uacrypto.load_private_key(key_file)
    else:
        key = generate_private_key()
        key_file.write_bytes(dump_private_key_as_pem(key))
    key_file.chmod(0o600)
    dns, ips = certificate_names(settings.endpoint)
    if cert_file.is_file() and _certificate_fits(await uacrypto.load_certificate(cert_file), app_uri, dns, ips):
        return cert_file, key_file
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(app_uri)]
    names += [x509.DNSName(d) for d in dns] + [x509.IPAddress(ipaddress.ip_address(i)) for i in ips]
    cert = generate_self_signed_app_certificate(
        key,
        app_uri,
        {"organizationName": "GWC", "commonName": "GWC OPC UA gateway"},
        names,
        extended=[ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH],
        days=365,
    )
    cert_file.write_bytes(cert.public_bytes(encoding=Encoding.DER))
    return cert_file, key_file


def identity_tokens(settings: OpcuaSettings) -> list[type]:
    tokens: list[type] = [ua.UserNameIdentityToken, ua.X509IdentityToken]
    return ([ua.AnonymousIdentityToken] if settings.anonymous else []) + tokens


def security_policies(settings: OpcuaSettings) -> list[ua.SecurityPolicyType]:
    """An unsecured endpoint only for anonymous browsing; otherwise SignAndEncrypt alone."""
    return ([ua.SecurityPolicyType.NoSecurity] if settings.anonymous else []) + SECURE_POLICIES
