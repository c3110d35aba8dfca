"""`gwc bench order`: a plant's order book on a private cell (issue 38).

An order of N milled pawns (gwc/lot/scripts/mill_and_measure.py: mill on any mill, measure on any CMM)
goes through a private cell of M machines (dummy mills and simulated CMMs that need no homing), run as
`gwc start` runs a cell: the host's agent starts the modules and admits the lot scripts
(gwc/lot/admission.py), the embedded database unless a URL is given. The operator imports the whole
order ahead and exports parts as they finish. Sampled every half second:

* the whole cell's memory: the proportional set size (PSS, shared pages split among their users) of
  every process of the cell, the database's included: what the cell costs the host;
* the database's connections against its max_connections;
* lots waiting while a machine that can serve them is idle: a queued request whose machines have all
  been Idle and unreserved for a second, asked more than a second ago (MSCHED binds in milliseconds);
* lot scripts running at once.

At the end: lots per second, `gwc check` (every invariant), failed lots.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import click
import psycopg

from gwc import db
from gwc.agent import control as agent_control
from gwc.budget import plan
from gwc.check import check_cell
from gwc.client.orders import decide, enter_order
from gwc.client.session import bench_context
from gwc.errors import GwcError
from gwc.soak.cell import PrivateCell

SAMPLE_S = 0.5
WAITING_SQL = """
SELECT r.request_key, r.entity_id, r.op_type, r.machine_id,
       round(extract(epoch FROM clock_timestamp() - r.requested_at)::numeric, 2) AS waited_s,
       EXISTS (SELECT 1 FROM accept_types a WHERE a.machine_id = r.machine_id AND a.op_type = r.op_type) AS accepts
  FROM request_machines r
 WHERE r.requested_at < clock_timestamp() - interval '1 second'
   AND NOT EXISTS (
       SELECT 1 FROM request_machines r2 JOIN machine_status s USING (machine_id)
        WHERE r2.request_key = r.request_key
          AND (s.status <> 'Idle' OR s.updated_at > clock_timestamp() - interval '1 second'
               OR EXISTS (SELECT 1 FROM reserved_machines m WHERE m.machine_id = r2.machine_id)))
 ORDER BY r.request_key LIMIT 3
"""


@dataclass
class OrderRun:
    """One order's figures (the JSON of `gwc bench order --json`)."""

    parts: int
    machines: int
    mills: int
    cmms: int
    max_running: int
    seconds: float = 0.0
    lots_per_s: float = 0.0
    exported: int = 0
    failed: int = 0
    peak_memory_mb: float = 0.0
    peak_connections: int = 0
    max_connections: int = 0
    peak_scripts: int = 0
    idle_while_waiting: int = 0  # samples in which a lot waited while a machine that could serve it was idle
    idle_while_waiting_examples: list[dict[str, Any]] = field(default_factory=list)  # the first few
    check_ok: bool = False
    check_failures: list[str] = field(default_factory=list)


def machines_for(n: int, run_time: float, measure_time: float) -> tuple[list[dict[str, Any]], int, int]:
    """n machines: a quarter CMMs (at least one), the rest mills."""
    cmms = max(1, math.ceil(n / 4))
    mills = max(1, n - cmms)
    specs: list[dict[str, Any]] = [{"id": f"mill{i}", "kind": "dummy", "run_time": run_time} for i in range(mills)]
    specs += [
        {
            "id": f"cmm{i}",
            "kind": "cmm",
            "homing_alarm": False,
            "serial": {"port": "sim", "baudrate": 115200, "timeout": 5.0},
            "sim": {"measure_time": measure_time, "pattern": "P"},
        }
        for i in range(cmms)
    ]
    return specs, mills, cmms


def pss_kb(pid: int) -> int:
    """A process's proportional set size in kB (0 if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


def database_pids(cell: PrivateCell) -> set[int]:
    """The embedded cluster's postmaster and its children (none for an external database)."""
    try:
        postmaster = int((cell.cfg.pg_dir / "postmaster.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return set()
    pids = {postmaster}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == postmaster:
                    pids.add(int(d.name))
    return pids


def run_order(
    var: Path,
    parts: int,
    n_machines: int,
    run_time: float,
    measure_time: float,
    max_running: int,
    database_url: str | None,
    log: logging.Logger,
    timeout: float,
) -> OrderRun:
    specs, mills, cmms = machines_for(n_machines, run_time, measure_time)
    cell = PrivateCell(var, specs, log, database_url=database_url, policy="fifo", agent=True)
    if max_running:
        cell.cfg.raw["lots"] = {"max_running": max_running}
        (cell.cfg.path).write_text(cell.cfg.path.read_text() + f"\n[lots]\nmax_running = {max_running}\n")
    budget = plan(cell.cfg)
    run = OrderRun(parts, len(specs), mills, cmms, budget.running, max_connections=budget.max_connections)
    try:
        cell.start()
        assert cell.bus is not None
        t0 = time.monotonic()
        made = enter_order(cell.cfg, log, cell.bus, "NJIT", [("milled_pawn", parts)])
        entities = [e for lot in made["lots"] for e in lot["entities"]]
        for e in entities:  # the whole order's stock brought in ahead (docs/lot-scripts.md, Admission)
            decide(cell.bus, e, "import", "bench")
        deadline = t0 + timeout
        with psycopg.connect(db.database_url(cell.cfg), autocommit=True) as conn:
            while time.monotonic() < deadline:
                states: dict[int, str] = dict(
                    conn.execute(
                        "SELECT entity_id, state FROM lot_status WHERE entity_id = ANY(%s)", (entities,)
                    ).fetchall()
                )
                for e, s in states.items():
                    if s == "waiting_export":
                        with contextlib.suppress(GwcError):
                            decide(cell.bus, e, "export", "bench")
                run.exported = sum(1 for s in states.values() if s == "exported")
                run.failed = sum(1 for s in states.values() if s == "failed")
                if run.exported + run.failed == parts:
                    break
                pids = set(cell.pids()) | database_pids(cell)
                run.peak_memory_mb = max(run.peak_memory_mb, sum(pss_kb(p) for p in pids) / 1024)
                row = conn.execute("SELECT count(*) FROM pg_stat_activity WHERE datname = current_database()")
                run.peak_connections = max(run.peak_connections, int(row.fetchone()[0]))  # type: ignore[index]
                waiting = conn.execute(WAITING_SQL).fetchall()
                if waiting:
                    run.idle_while_waiting += 1
                    if len(run.idle_while_waiting_examples) < 5:
                        keys = ("request_key", "entity_id", "op_type", "machine_id", "waited_s", "accepts")
                        run.idle_while_waiting_examples.append(dict(zip(keys, map(str, waiting[0]), strict=True)))
                modules = agent_control.call(cell.cfg, "status")["modules"]
                scripts = sum(1 for m in modules if m["module"].startswith("lot:") and m["state"] == "RUNNING")
                run.peak_scripts = max(run.peak_scripts, scripts)
                time.sleep(SAMPLE_S)
            run.seconds = time.monotonic() - t0
            run.lots_per_s = run.exported / run.seconds if run.seconds else 0.0
            breaches = check_cell(cell.cfg, conn, cell.bus, settle=3.0)
        run.check_failures = [str(b) for b in breaches]
        run.check_ok = not breaches
    finally:
        cell.stop()
    return run


@click.command("order")
@click.option("--parts", type=click.IntRange(1, 100_000), default=1000, show_default=True, help="Milled pawns ordered.")
@click.option("--machines", type=click.IntRange(2, 200), default=20, show_default=True, help="Mills and CMMs.")
@click.option("--run-time", type=float, default=0.2, show_default=True, help="Seconds a milling takes.")
@click.option("--measure-time", type=float, default=0.2, show_default=True, help="Seconds a measurement takes.")
@click.option("--max-running", type=int, default=0, help="[lots] max_running (0: the default, 4 per machine).")
@click.option(
    "--dir",
    "where",
    type=click.Path(file_okay=False, path_type=Path),
    help="The private cell's folder (default: var/bench-order); emptied first.",
)
@click.option("--timeout", type=float, default=1800.0, show_default=True, help="Give up after this many seconds.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as JSON.")
def command(
    parts: int,
    machines: int,
    run_time: float,
    measure_time: float,
    max_running: int,
    where: Path | None,
    timeout: float,
    as_json: bool,
) -> None:
    """An order of PARTS milled pawns through a private cell of MACHINES machines: the whole cell's peak
    memory, database connections, scripts at once, lots waiting while a machine could serve them, lots
    per second, and `gwc check`. Uses $GWC_DATABASE_URL if set, else an embedded cluster of its own."""
    cfg, log = bench_context()
    var = where or cfg.var / "bench-order"
    if var.exists():
        shutil.rmtree(var)
    url = os.environ.get("GWC_DATABASE_URL")
    try:
        run = run_order(var, parts, machines, run_time, measure_time, max_running, url, log, timeout)
    finally:
        shutil.rmtree(var, ignore_errors=True)
    if as_json:
        click.echo(json.dumps(asdict(run), indent=1))
        return
    click.echo(
        f"{run.parts} milled pawns on {run.machines} machines ({run.mills} mills, {run.cmms} CMMs), "
        f"at most {run.max_running} lot scripts at once"
    )
    click.echo(f"  exported {run.exported}, failed {run.failed} in {run.seconds:.1f} s: {run.lots_per_s:.1f} lots/s")
    click.echo(f"  peak memory of the whole cell {run.peak_memory_mb:.0f} MB (PSS, database included)")
    click.echo(
        f"  peak database connections {run.peak_connections} of {run.max_connections} "
        f"({100 * run.peak_connections / run.max_connections:.0f} %); peak lot scripts {run.peak_scripts}"
    )
    click.echo(f"  samples with a lot waiting while a machine could serve it: {run.idle_while_waiting}")
    click.echo(f"  gwc check: {'held' if run.check_ok else '; '.join(run.check_failures)}")
    if run.failed or not run.check_ok:
        raise GwcError("the order did not go through cleanly (see above)")
