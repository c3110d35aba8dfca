"""Machines: `gwc machine start|stop ID` and `gwc machine status` (the thesis's MSTT screen, Figure 6.7).

Starting and stopping a machine are the ME_START and ME_SHUT conversations with its WC (6.3.2.1-2),
so a machine joins or leaves the running cell without anything else being restarted. `start` also
brings up the machine's processes (simulator, ME, WC) if they are not running, which is how a pair
that died rejoins the cell. The status screen reads MACHINE_STATUS (reads are free) and shows
whether each machine's WC is on the bus.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import click
import psycopg

from gwc import cell, db
from gwc.config import Config
from gwc.errors import ModuleError
from gwc.hi import context, json_option, table
from gwc.ipc.bus import BlockingBus
from gwc.module import module_name

SEE_WC = 2.0  # how long to look for a WC on the bus before deciding its processes must be started


@click.group("machine")
def machine_group() -> None:
    """Start, stop and look at the cell's machines (their WC/ME pairs)."""


def _on_bus(bus: BlockingBus, name: str, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while name not in bus.peers():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


@machine_group.command("start")
@click.argument("machine_id")
@click.option(
    "--timeout",
    default=600.0,
    show_default=True,
    help="Seconds to wait for the machine (a homing alarm waits for the operator).",
)
def machine_start(machine_id: str, timeout: float) -> None:
    """Start machine MACHINE_ID: its processes if they are down, then ME_START (Shutdown -> Idle)."""
    cfg, log = context()
    with cell.hi_bus(cfg, log) as bus:
        start_machine(cfg, bus, machine_id, click.echo, timeout)


def start_machine(cfg: Config, bus: BlockingBus, machine_id: str, say: Callable[[str], None], timeout: float) -> str:
    """The machine's processes if its WC is not on the bus, then ME_START; returns how it ended."""
    cfg.machine(machine_id)  # ConfigError naming the known machines
    wc = module_name("wc", machine_id)
    if not _on_bus(bus, wc, SEE_WC):
        cell.start_procs(cfg, cell.machine_procs(cfg, machine_id), bus, say)
    say(
        f"{wc}: ME_START (a machine that must be homed raises its alarm now: "
        "`gwc alarm list`, then `gwc alarm clear N` once it is done)"
    )
    done = cell.startup(bus, wc, "ME_START", timeout=timeout)
    say(f"{wc}: {done}")
    return done


@machine_group.command("stop")
@click.argument("machine_id")
@click.option("--timeout", default=60.0, show_default=True, help="Seconds to wait for the WC's answer.")
def machine_stop(machine_id: str, timeout: float) -> None:
    """Shut machine MACHINE_ID down (ME_SHUT); a machine in a run shuts down when the run is over."""
    cfg, log = context()
    with cell.hi_bus(cfg, log) as bus:
        click.echo(f"{module_name('wc', machine_id)}: {stop_machine(cfg, bus, machine_id, timeout)}")


def stop_machine(cfg: Config, bus: BlockingBus, machine_id: str, timeout: float) -> str:
    """ME_SHUT to the machine's WC; returns how it ended."""
    cfg.machine(machine_id)
    wc = module_name("wc", machine_id)
    if not _on_bus(bus, wc, SEE_WC):
        raise ModuleError(f"{wc} is not on the bus: the machine is not running")
    return cell.shutdown(bus, wc, "ME_SHUT", timeout=timeout)


@machine_group.command("status")
@json_option
def machine_status(as_json: bool) -> None:
    """Every machine: status, recipe, run, start and end time, what it accepts, its WC on the bus."""
    cfg, log = context()
    with cell.hi_bus(cfg, log) as bus:
        time.sleep(cfg.bus.heartbeat)  # every module's hello has come once
        peers = bus.peers()
    with db.connect(cfg, role="hi", log=log) as conn:
        rows = machine_rows(conn, cfg, set(peers))
    table(
        rows,
        [
            "machine_id",
            "kind",
            "status",
            "recipe_id",
            "machine_run_id",
            "start_time",
            "end_time",
            "accepts",
            "wc",
            "note",
        ],
        as_json,
    )


def machine_rows(conn: psycopg.Connection[Any], cfg: Config, peers: set[str]) -> list[dict[str, Any]]:
    """MSTT's rows: each configured machine's MACHINE_STATUS, kind, accept types and whether its WC is on the bus."""
    cur = conn.execute(
        "select s.machine_id, c.kind, s.status, s.recipe_id, s.machine_run_id, s.start_time, s.end_time, "
        "coalesce((select string_agg(a.op_type, ',' order by a.op_type) from accept_types a "
        "          where a.machine_id = s.machine_id), '') as accepts, s.note "
        "from machine_status s join me_config c using (machine_id) order by s.machine_id"
    )
    names = [d.name for d in cur.description or []]
    rows = [dict(zip(names, r)) for r in cur.fetchall()]
    conn.rollback()
    configured = {m.id for m in cfg.machines}
    rows = [r for r in rows if r["machine_id"] in configured] if configured else rows
    for r in rows:
        r["wc"] = "on bus" if module_name("wc", r["machine_id"]) in peers else "-"
        for k in ("start_time", "end_time"):
            r[k] = r[k].strftime("%Y-%m-%d %H:%M:%S") if r[k] else None
    return rows


commands = [machine_group]
