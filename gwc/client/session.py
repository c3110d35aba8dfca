"""What every client conversation stands on: the HI's bus and database attachment, who acts, waiting
for a server to be on the bus, and a conversation of one question and one answer."""

from __future__ import annotations

import getpass
import logging
import os
import time
from pathlib import Path
from typing import Any

import click
import psycopg

from gwc import db
from gwc.cell import hi_bus
from gwc.config import Config, load_config
from gwc.errors import GwcError
from gwc.hostuser import become_cell_user, cell_user_reaches
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message
from gwc.log import open_log
from gwc.retry import Deadline

ON_BUS_WAIT = 3.0  # how long to wait to see a server on the bus before saying it is not running
ANSWER = 10.0  # a server's answer to one question

__all__ = [
    "ANSWER",
    "ON_BUS_WAIT",
    "ask",
    "bench_context",
    "context",
    "hi_bus",
    "hi_conn",
    "need_server",
    "on_bus",
    "operator",
    "rows_of",
]


def context(name: str = "hi", caps: tuple[int, ...] = (), drop: bool = True) -> tuple[Config, logging.Logger]:
    """The configuration and a client's log (var/log/<name>.log). Run as root, the command first becomes
    the cell's user, keeping capabilities `caps` alone (gwc.hostuser). `drop=False`: the benches and
    the soak, whose private cells run as whoever starts them: they become the cell's user only if it
    can reach the folders they were given (`--dir`), else stay as they are."""
    cfg = load_config()
    if drop or all(cell_user_reaches(cfg, p) for p in _folders_given()):
        become_cell_user(cfg, caps)
    return cfg, open_log(name, cfg.log_dir, cfg.level_of(name))


def bench_context(name: str = "bench", caps: tuple[int, ...] = ()) -> tuple[Config, logging.Logger]:
    """context() for a benchmark or the soak (`name`): its private cell runs as whoever starts it, so it
    becomes the cell's user only if that user can reach the folders it was given (drop=False); keeping
    `caps` (a bench whose cell runs its lot scripts as a user of their own keeps the agent's)."""
    return context(name, caps, drop=False)


def _folders_given() -> list[Path]:
    """The paths among the running click command's parameters (a bench's --dir)."""
    ctx = click.get_current_context(silent=True)
    return [v for v in (ctx.params.values() if ctx else ()) if isinstance(v, Path)]


def operator() -> str:
    """Who the HI acts for, as the cell records it (alarm history, recipe versions, lot decisions)."""
    try:
        return f"{getpass.getuser()}@hi.{os.getpid()}"
    except (KeyError, OSError):
        return f"{os.getuid()}@hi.{os.getpid()}"


def hi_conn(cfg: Config, log: logging.Logger) -> psycopg.Connection[Any]:
    """The Human Interface's connection, as role gwc_hi (it owns orders, customers, products, scripts)."""
    return db.connect(cfg, role="hi", log=log)


def rows_of(conn: psycopg.Connection[Any], sql: str, *params: Any) -> list[dict[str, Any]]:
    """One read as a list of dicts (column -> value), its transaction ended."""
    cur = conn.execute(sql, params)
    cols = [d.name for d in cur.description or []]
    rows = [dict(zip(cols, r)) for r in cur.fetchall()]
    conn.rollback()
    return rows


def on_bus(bus: BlockingBus, name: str, timeout: float = ON_BUS_WAIT) -> bool:
    """Whether module `name` is (or, within `timeout`, comes) on the bus."""
    deadline = Deadline(timeout)
    while name not in bus.peers():
        if deadline.expired:
            return False
        time.sleep(0.05)
    return True


def need_server(bus: BlockingBus, name: str, what: str) -> None:
    """Fail in one line unless server `name` is on the bus (the cell is started)."""
    if not on_bus(bus, name):
        raise GwcError(f"the {what} ({name}) is not on the bus: start the cell with `gwc start`")


def ask(bus: BlockingBus, cls: str, first: Message, to: str, timeout: float | None = ANSWER) -> Message:
    """A conversation of one question to `to` and its one answer (ConversationTimeout if none comes)."""
    conv, batch = bus.request(cls, first, to=to, timeout=timeout)
    conv.end()
    return batch.first
