"""The cell database's names and where it is found: the database, its roles, the embedded cluster's
socket and port (etc/cell.toml [database] port)."""

from __future__ import annotations

from pathlib import Path

from gwc.config import Config

DB_NAME = "gwc"
SUPERUSER = "gwc"
LOT_ROLE = "lot"  # lot scripts' role: logs in as itself, with a connection limit (schema.limit_lot_connections)
SOCKET_MAX = 107  # sun_path limit on Linux, including the terminating NUL


def socket_dir(cfg: Config) -> Path:
    """The embedded cluster's socket and lock: a folder of its own, var/run stays the cell's alone."""
    return cfg.run_dir / "pg"


def socket_path(cfg: Config) -> Path:
    return socket_dir(cfg) / f".s.PGSQL.{db_port(cfg)}"


def db_port(cfg: Config) -> int:
    return int(cfg.raw.get("database", {}).get("port", 5432))
