"""The cell's database connections, planned (docs/performance.md, *The order book*): the modules (one
connection per server, gateway and WC) and the operator's commands and screens always get theirs; lot
scripts share what is left, under a database role whose connection limit says so (gwc.db applies it),
so that even several hosts' agents together cannot take the operator's connections; and one agent runs
at most `Budget.running` lot scripts at once (gwc/lot/admission.py queues the rest).
"""

from __future__ import annotations

from dataclasses import dataclass

from gwc.config import OPTIONAL_MODULES, SERVER_MODULES, Config
from gwc.errors import ConfigError

# What the embedded cluster allows when cell.toml does not say (gwc.db.DEFAULT_SETTINGS reads it here).
MAX_CONNECTIONS = 200
# PostgreSQL keeps superuser_reserved_connections (3 by default) for its superuser: never the cell's.
SUPERUSER_RESERVED = 3
# The operator's commands (one connection each, while they run), consoles and gateways beyond the
# modules': kept free whatever the lot scripts do.
OPERATOR_RESERVE = 20
# Lot scripts one agent runs at once when cell.toml does not say: enough to keep every machine busy
# (a lot waits for its machine while another runs, and one more finishes or waits for export), few
# enough that a plant's order book costs rows, not processes.
PER_MACHINE = 4
MIN_RUNNING = 8


@dataclass(frozen=True)
class Budget:
    """The cell's database connections, planned: who may hold how many."""

    max_connections: int  # the server's limit
    modules: int  # held by the cell's modules: a server, the gateway, a WC each
    operator: int  # kept for the operator's commands and screens
    lots: int  # what lot scripts may hold together (the gwc_lot role's connection limit)
    running: int  # lot scripts one agent runs at once

    def describe(self) -> str:
        return (
            f"at most {self.running} lot scripts at once (database connections: {self.max_connections}; "
            f"modules {self.modules}, operator {self.operator}, superuser {SUPERUSER_RESERVED}, "
            f"lot scripts {self.lots})"
        )


def max_connections(cfg: Config) -> int:
    """The database server's connection limit: cell.toml's [database.settings] max_connections for the
    embedded cluster, or [database] max_connections for a server the plant runs (default PostgreSQL's 100)."""
    database = cfg.raw.get("database", {})
    if cfg.database_url and "max_connections" in database:
        value = database["max_connections"]
    elif cfg.database_url:
        value = 100
    else:
        value = database.get("settings", {}).get("max_connections", MAX_CONNECTIONS)
    if type(value) is not int or value < 10:
        raise ConfigError(f"database max_connections must be a whole number of at least 10, got {value!r}")
    return value


def plan(cfg: Config) -> Budget:
    """The budget of this cell: modules and operator first, lot scripts the rest ([lots] max_running
    bounds one agent's scripts further). ConfigError when the modules' share leaves nothing for lots."""
    limit = max_connections(cfg)
    modules = len([m for m in cfg.modules if m.name in SERVER_MODULES + OPTIONAL_MODULES]) + len(cfg.machines)
    lots = limit - SUPERUSER_RESERVED - OPERATOR_RESERVE - modules
    if lots < 1:
        raise ConfigError(
            f"the database allows {limit} connections, and the cell's {modules} modules and the operator's "
            f"{OPERATOR_RESERVE} leave none for lot scripts: raise [database.settings] max_connections"
        )
    wanted = cfg.raw.get("lots", {}).get("max_running", 0)
    if type(wanted) is not int or wanted < 0:
        raise ConfigError(f"lots.max_running must be a whole number (0: as many as the machines want), got {wanted!r}")
    running = wanted or max(MIN_RUNNING, PER_MACHINE * len(cfg.machines))
    return Budget(limit, modules, OPERATOR_RESERVE, lots, min(running, lots))
