"""Machines: ME_START and ME_SHUT with a machine's WC (6.3.2.1-2), bringing up its processes first when
they are down, and the machines' status (MACHINE_STATUS, and whether each WC is on the bus)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import psycopg

from gwc import cell
from gwc.client.session import ANSWER, ask, on_bus, operator
from gwc.config import Config
from gwc.errors import ConfigError, GwcError, ModuleError, Refused
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import module_name

SEE_WC = 2.0  # how long to look for a WC on the bus before deciding its processes must be started
HEAR_REMOTE_WC = 30.0  # s: a WC on another host is waited for this long (its host may be just back on the network)
START_TIMEOUT = 600.0  # a homing alarm waits for the operator
STOP_TIMEOUT = 60.0

__all__ = ["heard_peers", "machine_rows", "machines_on", "maintenance_done", "start_machine", "stop_machine"]


def start_machine(
    cfg: Config,
    bus: BlockingBus,
    machine_id: str,
    say: Callable[[str], None] = lambda s: None,
    timeout: float = START_TIMEOUT,
) -> str:
    """ME_START with the machine's WC (Shutdown -> Idle), after spawning whichever of its processes
    (simulator, ME, WC) is down, by their pid files: an ME dead behind a live WC too (on the machine's
    own host only; from another host it only asks the WC). Returns how it
    ended ("started", "already started"); ModuleError if refused. `say` hears each step, that a homing
    alarm may now wait for the operator, and the end."""
    spec = cfg.machine(machine_id)  # ConfigError naming the known machines
    wc = module_name("wc", machine_id)
    if cfg.placed_here(spec):  # another host's machine: its processes are that host's (docs/deploying.md)
        procs = cell.machine_procs(cfg, machine_id)
        if on_bus(bus, wc, SEE_WC):  # a WC on the bus runs, whoever started it (its pid file may be elsewhere)
            procs = [p for p in procs if p.kind != "wc"]
        cell.start_procs(cfg, procs, bus, say)
    elif not on_bus(bus, wc, HEAR_REMOTE_WC):
        raise ModuleError(f"{wc} is not on the bus: its host {spec.host} runs it (`gwc start` there)")
    say(
        f"{wc}: ME_START (a machine that must be homed raises its alarm now: "
        "`gwc alarm list`, then `gwc alarm clear N` once it is done)"
    )
    done = cell.startup(bus, wc, Conv.ME_START, timeout=timeout)
    say(f"{wc}: {done}")
    return done


def machines_on(cfg: Config, host: str) -> list[str]:
    """The machines placed on [[host]] `host`, in cell.toml order; ConfigError for an unknown host."""
    if host not in {h.name for h in cfg.hosts}:
        raise ConfigError(f"no host {host!r} in the cell (hosts: {', '.join(h.name for h in cfg.hosts) or 'none'})")
    return [m.id for m in cfg.machines if m.host == host]


def stop_machine(cfg: Config, bus: BlockingBus, machine_id: str, timeout: float = STOP_TIMEOUT) -> str:
    """ME_SHUT with the machine's WC; a machine in a run shuts down when the run is over. Returns how it
    ended; ModuleError if its WC is not on the bus."""
    cfg.machine(machine_id)
    wc = module_name("wc", machine_id)
    if not on_bus(bus, wc, SEE_WC):
        raise ModuleError(f"{wc} is not on the bus: the machine is not running")
    return cell.shutdown(bus, wc, Conv.ME_SHUT, timeout=timeout)


def heard_peers(cfg: Config, bus: BlockingBus) -> set[str]:
    """Who is on the bus, once every module's hello has come (one heartbeat after joining)."""
    time.sleep(cfg.bus.heartbeat)
    return set(bus.peers())


# The Machine Status screen's columns (MSTT), as machine_rows names them: the console's and `gwc machine status`.
MACHINE_COLUMNS = (
    "machine_id",
    "kind",
    "status",
    "recipe_id",
    "machine_run_id",
    "start_time",
    "end_time",
    "accepts",
    "wc",
    "runs",
    "maint_every",
    "scrap",
)


def machine_rows(conn: psycopg.Connection[Any], cfg: Config, peers: set[str]) -> list[dict[str, Any]]:
    """MSTT's rows: each configured machine's MACHINE_STATUS, kind, accept types and whether its WC is among
    `peers` (on the bus). On the caller's connection (a screen keeps one open)."""
    cur = conn.execute(
        "select s.machine_id, c.kind, s.status, s.recipe_id, s.machine_run_id, s.start_time, s.end_time, "
        "coalesce((select string_agg(a.op_type, ',' order by a.op_type) from accept_types a "
        "          where a.machine_id = s.machine_id), '') as accepts, s.note, "
        "s.runs_since_maintenance as runs, s.maintenance_every as maint_every, s.scrap_count as scrap "
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


def maintenance_done(bus: BlockingBus, machine_id: str, timeout: float = ANSWER, by: str | None = None) -> int:
    """MAINT_DONE to the Machine Server (1.4.2's maintenance schedule): the machine was maintained, its
    run count starts again. Returns the count before; GwcError for an unknown machine. `by`: who
    acts, as recorded (the HI's operator unless said)."""
    first = message(Msg.MAINT_DONE, machine_id=machine_id, by=by or operator())
    ack = ask(bus, Conv.MAINT_DONE, first, "ms", timeout)
    if ack.ack_code == AckCode.UNKNOWN:
        raise GwcError(f"unknown machine {machine_id!r} (see `gwc machine status`)")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"the Machine Server did not take the maintenance of {machine_id}")
    return int(ack.runs or 0)
