"""Machines: `gwc machine start|stop ID` and `gwc machine status` (the thesis's MSTT screen, Figure 6.7).

Starting and stopping a machine are the ME_START and ME_SHUT conversations with its WC (6.3.2.1-2),
so a machine joins or leaves the running cell without anything else being restarted. `start` also
brings up the machine's processes (simulator, ME, WC) if they are not running, which is how a pair
that died rejoins the cell. The status screen reads MACHINE_STATUS (reads are free) and shows
whether each machine's WC is on the bus, and its books (1.4.2): runs since maintenance, the
maintenance interval, parts scrapped; `maintenance-done` restarts the count (MAINT_DONE).
The conversations are gwc.client.machines'.
"""

from __future__ import annotations

import click

from gwc.client.machines import (
    MACHINE_COLUMNS,
    START_TIMEOUT,
    STOP_TIMEOUT,
    heard_peers,
    machine_rows,
    machines_on,
    maintenance_done,
    start_machine,
    stop_machine,
)
from gwc.client.session import hi_bus, hi_conn
from gwc.errors import GwcError, ModuleError
from gwc.hi import context, json_option, table
from gwc.module import module_name

STATUS_COLUMNS = [*MACHINE_COLUMNS, "note"]


@click.group("machine")
def machine_group() -> None:
    """Start, stop and look at the cell's machines (their WC/ME pairs)."""


@machine_group.command("start")
@click.argument("machine_ids", nargs=-1)
@click.option("--on", "host", help="Every machine placed on this [[host]] too (a host back on the network).")
@click.option(
    "--timeout",
    default=START_TIMEOUT,
    show_default=True,
    help="Seconds to wait for each machine (a homing alarm waits for the operator).",
)
def machine_start(machine_ids: tuple[str, ...], host: str | None, timeout: float) -> None:
    """Start each machine MACHINE_ID (and those on --on HOST) in turn: its processes if they are down,
    then ME_START (Shutdown -> Idle). One that fails is reported and the others are still started."""
    cfg, log = context()
    ids = list(dict.fromkeys([*machine_ids, *(machines_on(cfg, host) if host else [])]))
    if not ids:
        raise click.UsageError("name a machine, or --on HOST")
    for machine_id in ids:
        cfg.machine(machine_id)  # every name checked before any machine is started
    failed = []
    with hi_bus(cfg, log) as bus:
        for machine_id in ids:
            try:
                start_machine(cfg, bus, machine_id, click.echo, timeout)
            except GwcError as e:
                if len(ids) == 1:
                    raise  # its own line and exit code
                click.echo(f"{machine_id}: {e}", err=True)
                failed.append(machine_id)
    if failed:
        raise ModuleError(f"not started: {', '.join(failed)}")


@machine_group.command("stop")
@click.argument("machine_id")
@click.option("--timeout", default=STOP_TIMEOUT, show_default=True, help="Seconds to wait for the WC's answer.")
def machine_stop(machine_id: str, timeout: float) -> None:
    """Shut machine MACHINE_ID down (ME_SHUT); a machine in a run shuts down when the run is over."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        done = stop_machine(cfg, bus, machine_id, timeout)
    click.echo(f"{module_name('wc', machine_id)}: {done}")


@machine_group.command("status")
@json_option
def machine_status_command(as_json: bool) -> None:
    """Every machine: status, recipe, run, start and end time, what it accepts, its WC on the bus."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        peers = heard_peers(cfg, bus)
    with hi_conn(cfg, log) as conn:
        rows = machine_rows(conn, cfg, peers)
    table(rows, STATUS_COLUMNS, as_json)


@machine_group.command("maintenance-done")
@click.argument("machine_id")
def machine_maintenance_done(machine_id: str) -> None:
    """The machine was maintained: its count of runs since maintenance starts again (MAINT_DONE)."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        runs = maintenance_done(bus, machine_id)
    click.echo(f"{machine_id} maintained after {runs} run(s): its count starts again")


commands = [machine_group]
