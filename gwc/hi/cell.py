"""Cell-level commands: the database, start/stop/status of the cell (STRT), running one module."""

from __future__ import annotations

import sys

import click

from gwc import cell, db
from gwc.agent import control as agent_control
from gwc.agent.agent import agent_name, run_agent
from gwc.agent.unit import systemd_unit
from gwc.config import load_config
from gwc.hi import context, json_option, table
from gwc.hostuser import AGENT_CAPS, STOP_CAPS, become_cell_user
from gwc.log import cap_output, open_log
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
        click.echo(f"embedded cluster running (socket in {db.socket_dir(cfg)})")
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
    """Start the cell: database, then this host's agent, which starts every module and keeps it running."""
    cfg, log = context(caps=AGENT_CAPS)
    cell.start_cell(cfg, log, say=click.echo)
    click.echo("cell started")


@click.command("stop")
@click.option("--keep-db", is_flag=True, help="Leave the embedded database running.")
def stop(keep_db: bool) -> None:
    """Stop lot scripts, then every module through the agent (SIGTERM, then SIGKILL), the agent, the database."""
    cfg, log = context(caps=STOP_CAPS)
    cell.stop_cell(cfg, log, say=click.echo, database=not keep_db)
    click.echo("cell stopped")


@click.command("status")
@json_option
def status(as_json: bool) -> None:
    """Each module of the cell: its state under the agent, pid, uptime, restarts, how it last ended."""
    cfg, _ = context()
    agent, rows = cell.cell_status(cfg)
    if not as_json:
        down = db.probe(cfg)
        where = f"embedded, {'running' if db.cluster_running(cfg) else 'stopped'}" if cfg.embedded else "external"
        click.echo(f"database: {where}, " + (f"DOWN ({down})" if down else "up"))
        click.echo(f"agent: {agent['name']} (pid {agent['pid']})" if agent else "agent: not running (unsupervised)")
    table(rows, ["module", "state", "pid", "uptime", "restarts", "last_exit"], as_json)


@click.command("restart")
@click.argument("modules", nargs=-1, required=True)
def restart(modules: tuple[str, ...]) -> None:
    """Restart MODULES (e.g. msched, wc:wc1) through this host's agent: stopped, then started again."""
    cfg, _ = context()
    agent_control.call(cfg, "restart", say=click.echo, names=list(modules))


@click.command("agent")
@click.option(
    "--systemd-unit", "unit", is_flag=True, help="Print a systemd unit that runs this host's agent, and exit."
)
def agent(unit: bool) -> None:
    """Run this host's agent in the foreground (`gwc start` starts it detached): it starts the host's
    modules, restarts the ones that die, and stops them on SIGTERM."""
    cfg, _ = context(caps=AGENT_CAPS)
    if unit:
        click.echo(systemd_unit(cfg), nl=False)
        return
    log = open_log(agent_name(cfg.host), cfg.log_dir, cfg.level_of("agent"))
    cap_output()
    sys.exit(run_agent(cfg, log))


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
    become_cell_user(load_config())  # run by hand as root: as the cell's user all the same
    sys.exit(run_module(module, machine, start=start_now, options=options))


commands = [db_group, start, stop, status, restart, agent, run]
