"""The web module's settings: the [web] section of cell.toml (docs/web.md, Settings)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gwc.config import Config
from gwc.errors import ConfigError

DEFAULT_LISTEN = "127.0.0.1:8443"


@dataclass(frozen=True)
class WebSettings:
    listen: str = DEFAULT_LISTEN  # HOST:PORT the HTTPS server listens on
    certificate: Path | None = None  # the plant's certificate (PEM); else the cell makes one in var/web/
    key: Path | None = None  # its private key (PEM)
    session_idle_s: float = 900.0  # a session unused this long is over
    session_max_s: float = 28800.0  # and any session after this long (a shift)
    lockout_after: int = 10  # wrong passwords for one user name, or from one address, within 10 minutes ...
    lockout_s: float = 300.0  # ... lock the login for that name or address this long after the last
    refresh: float = 2.0  # s between re-reads of the tables for the live pages (broadcasts wake it sooner)
    cert_dir: Path = Path()

    @property
    def host(self) -> str:
        return self.listen.rsplit(":", 1)[0].strip("[]")

    @property
    def port(self) -> int:
        return int(self.listen.rsplit(":", 1)[1])


def load_settings(cfg: Config) -> WebSettings:
    """The [web] section, checked: ConfigError naming the key that is wrong."""
    raw: dict[str, Any] = dict(cfg.raw.get("web", {}))
    known = set(WebSettings.__dataclass_fields__) - {"cert_dir"}
    unknown = set(raw) - known
    if unknown:
        raise ConfigError(f"{cfg.path}: [web] has unknown key(s) {', '.join(sorted(unknown))}")
    for name in ("certificate", "key"):
        if name in raw:
            p = Path(raw[name])
            raw[name] = p if p.is_absolute() else cfg.path.parent.parent / p
    if ("certificate" in raw) != ("key" in raw):
        raise ConfigError(f"{cfg.path}: [web] certificate and key go together (or neither: the cell makes one)")
    try:
        s = WebSettings(**raw, cert_dir=cfg.var / "web")
        port = s.port
    except (TypeError, ValueError, IndexError) as e:
        raise ConfigError(f'{cfg.path}: [web]: {e} (listen = "HOST:PORT")') from None
    if not 0 < port < 65536 or not s.host:
        raise ConfigError(f'{cfg.path}: [web] listen {s.listen!r}: give "HOST:PORT"')
    for name in ("session_idle_s", "session_max_s", "lockout_s", "refresh"):
        if float(getattr(s, name)) <= 0:
            raise ConfigError(f"{cfg.path}: [web] {name} must be above 0")
    if s.lockout_after < 1:
        raise ConfigError(f"{cfg.path}: [web] lockout_after must be 1 or more")
    return s
