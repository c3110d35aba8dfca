"""Cell-level commands: the database, start/stop/status of the cell (STRT), running one module."""

from __future__ import annotations

import sys

import click

from gwc import cell, db
from gwc.hi import context, json_option, table
from gwc.module import BUS_MODULES, MACHINE_PROCESSES, run_module


@click.group("db")
def db_group() -> None:
    """The cell database: the embedded cluster under var/pg, or $GWC_DATABASE_URL."""


@db_group.command("start")
def db_start() -> None:
    """Create (first time) and start the embedded PostgreSQL cluster, then apply the schema."""
    cfg, log = context()
    if not cfg.embedded:
        click.echo("using $GWC_DATABASE_URL: nothing to start")
    else:
        db.cluster_start(cfg, log)
        click.echo(f"embedded cluster running (socket in {cfg.run_dir})")
    db.init_schema(cfg, log)


@db_group.command("stop")
def db_stop() -> None:
    """Stop the embedded cluster (no-op if it is not running)."""
    cfg, log = context()
    if not cfg.embedded:
        click.echo("using $GWC_DATABASE_URL: nothing to stop")
        return
    db.cluster_stop(cfg, log)
    click.echo("embedded cluster stopped")


@db_group.command("init")
def db_init() -> None:
    """Apply sql/ (schema, procedures, roles, seed data); safe to run again."""
    cfg, log = context()
    db.init_schema(cfg, log)
    click.echo("schema applied")


@db_group.command("url")
def db_url() -> None:
    """Print the connection URL the cell uses (for psql)."""
    cfg, _ = context()
    click.echo(db.database_url(cfg))


@click.command("start")
def start() -> None:
    """Start the cell: database, servers (STARTUP each), machines' WC/ME processes. Idempotent."""
    cfg, log = context()
    cell.start_cell(cfg, log, say=click.echo)
    click.echo("cell started")


@click.command("stop")
@click.option("--keep-db", is_flag=True, help="Leave the embedded database running.")
def stop(keep_db: bool) -> None:
    """Stop every module (SIGTERM, then SIGKILL), remove pid files and queues, stop the database."""
    cfg, log = context()
    cell.stop_cell(cfg, log, say=click.echo, database=not keep_db)
    click.echo("cell stopped")


@click.command("status")
@json_option
def status(as_json: bool) -> None:
    """Each module of the cell: pid, alive or not, since when."""
    cfg, _ = context()
    rows = [
        {"module": s.name, "pid": s.pid, "alive": "yes" if s.alive else "no", "since": s.since if s.pid else None}
        for s in cell.cell_status(cfg)
    ]
    if not as_json and cfg.embedded:
        click.echo(f"database: embedded, {'running' if db.cluster_running(cfg) else 'stopped'}")
    table(rows, ["module", "pid", "alive", "since"], as_json)


@click.command("run", context_settings={"ignore_unknown_options": False})
@click.argument("module", type=click.Choice(sorted([*BUS_MODULES, *MACHINE_PROCESSES])))
@click.option("--machine", "machine", help="Machine id, for wc, me and cmmsim.")
@click.option("--start", "start_now", is_flag=True, help="Start at once, without waiting for a STARTUP conversation.")
@click.option(
    "--clean",
    is_flag=True,
    help="msched only: empty the request and reservation tables at start (the thesis's behaviour).",
)
def run(module: str, machine: str | None, start_now: bool, clean: bool) -> None:
    """Run one cell module in the foreground as this process (gwc start uses this)."""
    options = {"clean": True} if clean else None
    if clean and module != "msched":
        raise click.UsageError("--clean applies to msched only")
    sys.exit(run_module(module, machine, start=start_now, options=options))


commands = [db_group, start, stop, status, run]
