"""`gwc upgrade`: replace a redundant module by a new build while lots run (docs/deploying.md, 7).

`gwc upgrade status` says what this build speaks and runs with (wire versions, schema version), what
the database holds, and which wire version each module on the bus speaks: during a rolling upgrade
some speak the newer version, and the cell speaks the lowest of them until every host has moved.

`gwc upgrade handover NAME...` is the standby-first step for the active instances on this host: for
each leased module it waits until a standby stands by (a second session of the module's role holds a
connection), then stops the active instance (through this host's agent, which starts it again from
the package now installed: a standby of the new build; without an agent, SIGTERM to it), and waits
until a standby holds the lease and is on the bus. Run it with the new build installed, after the
standby hosts were upgraded (their standbys restarted), so that the instance taking over is new.
"""

from __future__ import annotations

import json
import os
import signal
import time
from typing import Any

import click
import psycopg

from gwc import schema
from gwc.agent import control as agent_control
from gwc.cell import hi_bus
from gwc.client.session import hi_conn
from gwc.config import Config
from gwc.errors import GwcError, ModuleError
from gwc.hi import context, json_option
from gwc.ipc import wire
from gwc.retry import Deadline


def leases(conn: psycopg.Connection[Any]) -> dict[str, dict[str, Any]]:
    rows = conn.execute("select name, epoch, holder, host, backend_pid from module_leases").fetchall()
    conn.rollback()
    return {r[0]: {"epoch": int(r[1]), "holder": r[2], "host": r[3], "backend_pid": r[4]} for r in rows}


def standbys(conn: psycopg.Connection[Any], name: str, holder_pid: int | None) -> int:
    """Sessions of the module's role (a leased module's role is its name) other than the holder's:
    its standbys, each holding the connection it tries the lease through."""
    app = f"gwc_{name}"
    row = conn.execute(
        "select count(*) from pg_stat_activity where application_name = %s and pid is distinct from %s",
        (app, holder_pid),
    ).fetchone()
    conn.rollback()
    return int(row[0]) if row else 0


@click.group("upgrade")
def upgrade() -> None:
    """Upgrade the cell while it runs: versions, and the standby-first handover."""


@upgrade.command("status")
@click.option("--listen", type=float, default=2.0, show_default=True, help="Seconds to hear the modules' beats.")
@json_option
def status(listen: float, as_json: bool) -> None:
    """This build's wire and schema versions, the database's, and the wire version each module speaks."""
    cfg, log = context()
    state: schema.SchemaState | None = None
    with hi_conn(cfg, log) as conn:
        state = schema.read(conn)
    bus = hi_bus(cfg, log)
    try:
        time.sleep(max(listen, 0.0))
        speaks = bus.bus.versions()
        speaking = bus.bus.speaking
    finally:
        bus.close()
    out = {
        "build": {"wire": [wire.MIN_VERSION, wire.VERSION], "schema": schema.SCHEMA_VERSION},
        "database": None if state is None else {"schema": state.version, "runs_builds_from": state.compatible_from},
        "runs_here": state is not None and state.runs(),
        "modules": dict(sorted(speaks.items())),
        "cell_speaks": speaking,
    }
    if as_json:
        click.echo(json.dumps(out, indent=1))
        return
    click.echo(f"this build: wire versions {wire.MIN_VERSION}..{wire.VERSION}, schema {schema.SCHEMA_VERSION}")
    if state is None:
        click.echo("database: records no schema version (apply this build's schema: `gwc db init`)")
    else:
        click.echo(
            f"database: schema {state.version}, runs builds of schema {state.compatible_from}..{state.version}"
            f" ({'this build runs with it' if state.runs() else state.problem()})"
        )
    by_version: dict[int, list[str]] = {}
    for name, v in speaks.items():
        by_version.setdefault(v, []).append(name)
    for v, names in sorted(by_version.items()):
        click.echo(f"wire {v}: {', '.join(sorted(names))}")
    click.echo(f"the cell speaks wire version {speaking}")


@upgrade.command("handover")
@click.argument("names", nargs=-1, required=True)
@click.option("--timeout", type=float, default=30.0, show_default=True, help="Seconds to wait at each step.")
def handover(names: tuple[str, ...], timeout: float) -> None:
    """Hand each named leased module over to a standby, then start this host's instance again."""
    cfg, log = context()
    for name in names:
        if not cfg.leased(name):
            raise GwcError(f"{name} runs without standbys (no `standby` or `lease` in cell.toml): no handover")
    bus = hi_bus(cfg, log)
    try:
        with hi_conn(cfg, log) as conn:
            for name in names:
                _handover(cfg, conn, bus, name, timeout)
    finally:
        bus.close()


def _handover(cfg: Config, conn: psycopg.Connection[Any], bus: Any, name: str, timeout: float) -> None:
    held = leases(conn).get(name)
    if held is None:
        raise ModuleError(f"{name}: no instance holds its lease (is it running?)")
    host, _, rest = str(held["holder"]).partition(":")
    pid = int(rest.split(":")[0])
    if host not in ("local", cfg.host or "local"):
        raise ModuleError(f"{name} is active on {host}: run `gwc upgrade handover {name}` there")
    deadline = Deadline(timeout)
    while standbys(conn, name, held["backend_pid"]) < 1:
        if deadline.expired:
            raise ModuleError(f"{name}: no standby stands by: start one (upgrade its host first) and try again")
        time.sleep(0.1)
    peer = bus.peers().get(name)
    old_inc = peer.inc if peer is not None else None
    began = time.monotonic()
    if agent_control.running(cfg):
        agent_control.call(cfg, "restart", names=[name], say=lambda s: click.echo(f"  {s}"))
    else:
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    deadline = Deadline(timeout)
    while True:
        now = leases(conn).get(name)
        peer = bus.peers().get(name)
        if now is not None and now["epoch"] > held["epoch"] and peer is not None and peer.inc != old_inc:
            break
        if deadline.expired:
            raise ModuleError(f"{name}: no standby took over within {timeout:.0f}s")
        time.sleep(0.05)
    speaks = bus.bus.versions().get(name)
    click.echo(
        f"{name}: handed over to {now['holder']} (epoch {now['epoch']}) in {time.monotonic() - began:.2f}s"
        f"{f'; it speaks wire version {speaks}' if speaks else ''}"
    )


commands = [upgrade]
