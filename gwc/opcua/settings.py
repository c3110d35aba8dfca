"""The gateway's settings: the [opcua] section of cell.toml (docs/opcua.md, Settings)."""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gwc.config import Config
from gwc.errors import ConfigError

DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840/gwc/"
SCRYPT_MAX_N = 2**20  # what a configured password hash may ask for at most (memory: N * r * 128 bytes)


@dataclass(frozen=True)
class OpcuaSettings:
    endpoint: str = DEFAULT_ENDPOINT
    anonymous: bool = True  # anonymous clients may browse and subscribe (never call methods)
    users: dict[str, str] = field(default_factory=dict)  # user name -> salted hash "scrypt$N$r$p$salt$hash"
    user_certificates: dict[str, Path] = field(default_factory=dict)  # user name -> DER/PEM certificate
    refresh: float = 1.0  # seconds between full re-reads of the tables (what no broadcast tells)
    keep_done: float = 300.0  # seconds an exported or failed entity stays in the address space
    method_timeout: float = 0.9  # longest a method waits for a module's answer (see COMPLETE_WAIT)
    cert_dir: Path = Path()  # the server's certificate and key, made when missing

    @property
    def namespace(self) -> str:
        return "urn:gwc:cell"


def parse_hash(stored: str) -> tuple[int, int, int, bytes, bytes]:
    """(N, r, p, salt, hash) of a stored password; ValueError saying what is wrong with it."""
    parts = stored.split("$")
    if len(parts) != 6 or parts[0] != "scrypt":
        raise ValueError('not a salted hash "scrypt$N$r$p$salt$hash" (`gwc key opcua-password` makes one)')
    n, r, p = (int(x) for x in parts[1:4])
    if not (1 < n <= SCRYPT_MAX_N and n & (n - 1) == 0 and 0 < r <= 32 and 0 < p <= 16):
        raise ValueError(f"scrypt parameters N={n} r={r} p={p} out of range (N a power of 2 up to {SCRYPT_MAX_N})")
    salt, digest = base64.b64decode(parts[4], validate=True), base64.b64decode(parts[5], validate=True)
    if len(salt) < 8 or len(digest) < 16:
        raise ValueError("salt or hash too short")
    return n, r, p, salt, digest


def load_settings(cfg: Config) -> OpcuaSettings:
    """The [opcua] section, checked: ConfigError naming the key that is wrong."""
    raw: dict[str, Any] = dict(cfg.raw.get("opcua", {}))
    known = set(OpcuaSettings.__dataclass_fields__) - {"cert_dir"}
    unknown = set(raw) - known
    if unknown:
        raise ConfigError(f"{cfg.path}: [opcua] has unknown key(s) {', '.join(sorted(unknown))}")
    if not str(raw.get("endpoint", DEFAULT_ENDPOINT)).startswith("opc.tcp://"):
        raise ConfigError(f"{cfg.path}: [opcua] endpoint must be an opc.tcp:// URL")
    certs = {}
    for user, path in dict(raw.pop("user_certificates", {})).items():
        p = Path(path)
        certs[str(user)] = p if p.is_absolute() else cfg.path.parent.parent / p
    try:
        s = OpcuaSettings(**raw, user_certificates=certs, cert_dir=cfg.var / "opcua")
    except TypeError as e:
        raise ConfigError(f"{cfg.path}: [opcua]: {e}") from None
    for user, stored in s.users.items():
        try:
            parse_hash(str(stored))
        except ValueError as e:
            raise ConfigError(
                f"{cfg.path}: [opcua] users.{user}: {e}: a password is kept as a salted hash, never in clear "
                "(`gwc key opcua-password` prints one to paste here)"
            ) from None
    for name in ("refresh", "keep_done", "method_timeout"):
        if float(getattr(s, name)) <= 0:
            raise ConfigError(f"{cfg.path}: [opcua] {name} must be above 0")
    return s
