"""`gwc bench cell`: the whole cell's cost per lot, its throughput, and how fast it routes around a death.

A private cell (gwc.soak.cell) with N dummy machines whose runs take no time runs M lots of the
soak's lot script, one lot at a time per machine (a lane each; with `--at-once K`, K lanes, each
lot on the next free machine in turn), so a lot never waits for a busy machine and everything it
waits for is the cell itself:

* overhead per lot: the lot script's own clock around its operation, from the machine request to
  the unreserve's answer (every conversation between: MACH_REQ, the Lot Server's state changes,
  SETUP_RUN, START_RUN, the run's RUN_COMPL, UNRESERVE), minus the machine's run time (zero);
  the phases come from the Figure 2 time stamps of the script's log;
* lots per second: M over the wall time from the first order to the last export, with the
  operator's import and export and one lot-script process per lot included;
* death to reroute: a lot may use either of two slower machines; while its run is on one, that
  machine's WC and ME are killed -9. The time from the kill to the Machine_Req_Comp that gives the
  lot the other machine (detection by the Machine Server's liveness watch, the lot noticing its
  machine shut down, unreserve, a new request, MSCHED binding the alternative).

The thesis's bar (3.0) is that "the computer is not the bottleneck": the overhead is what a real
machine's cycle has to dwarf.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import psycopg

from gwc import db
from gwc.agent import control as agent_control
from gwc.bench import brief, cpu_s, reaped_cpu_s, summary
from gwc.bench.heal import freeze_trials
from gwc.bench.logs import bound_to, phases, script_cpu
from gwc.cell import machine_procs
from gwc.check import check_cell
from gwc.client.orders import decide
from gwc.client.session import bench_context
from gwc.errors import GwcError
from gwc.hostuser import AGENT_CAPS, lot_group
from gwc.ipc.codes import LotState
from gwc.lot.entity import create_lot
from gwc.lot.run import spawn_lot_script
from gwc.retry import Deadline
from gwc.soak.cell import PrivateCell
from gwc.soak.driver import PRODUCT, SCRIPT_ID, SCRIPT_PATH

SLOW_RUN = 4.0  # seconds a run takes on the two machines of the death trials: long enough to die in
LOT_TIMEOUT = 120.0  # one lot, order to export, on a loaded shared machine
POLL = 0.01  # the operator's look at the lots, when lots per second are measured
SOLO_POLL = 0.05  # ... when one lot's own cost is: the operator's reads must not load the cell it measures
FINAL = (LotState.EXPORTED.value, LotState.FAILED.value)

# The phases of an operation, in order: the named events the lot library emits (gwc/lot/events.py),
# which the bench's lot script leaves in its timing file (gwc/lot/scripts/soak.py).
FLOOR_S = 30.0  # the resting floor is measured for at most this long

# A process that only wakes once a heartbeat on the cell's event loop, and prints the CPU its wake-ups took:
# what a wake-up costs on this machine at this time, whatever a module does in it.
_SLEEPER = """
import asyncio, sys, time
from gwc.ipc.eventloop import run
async def rest(beat, until):
    began = time.process_time()
    while time.monotonic() < until:
        await asyncio.sleep(beat)
    return time.process_time() - began
print(run(rest(float(sys.argv[1]), time.monotonic() + float(sys.argv[2]))))
"""


class CellBench:
    """One run of the benchmark on its own private cell (see the module docstring)."""

    counted = "xact_commit"  # which of pg_stat_database's transaction counters _commits() adds up

    def __init__(
        self,
        var: Path,
        machines: int,
        lots: int,
        solo: int,
        deaths: int,
        database_url: str | None,
        log: logging.Logger,
        say: Callable[[str], None],
        kernel_filter: bool = True,
        freezes: int = 0,
        idle_s: float = 60.0,
        at_once: int = 0,
        history: bool = True,
        lots_cfg: dict[str, Any] | None = None,
    ) -> None:
        self.var = var.resolve()
        self.history = history
        self.n = machines
        self.m = lots
        self.solo = solo
        self.deaths = deaths
        self.freezes = freezes
        self.idle_s = idle_s
        self.log = log
        self.say = say
        self.fast = [f"wc{i}" for i in range(1, machines + 1)]
        self.at_once = min(at_once, machines) if at_once > 0 else machines  # lots at work at a time
        self.slow = ["slow1", "slow2"] if deaths or freezes else []
        specs = [{"id": m, "kind": "dummy", "run_time": 0.0} for m in self.fast]
        specs += [{"id": m, "kind": "dummy", "run_time": SLOW_RUN} for m in self.slow]
        if self.var.exists():
            shutil.rmtree(self.var)
        # With the host's agent, as `gwc start` runs a cell: it announces a death the moment it happens.
        self.cell = PrivateCell(
            self.var,
            specs,
            log,
            database_url,
            bus={"kernel_filter": kernel_filter},
            agent=True,
            record={"history": history},  # the production record written, or not ([record] history)
            lots=lots_cfg,  # [lots]: the scripts' user, and whether its launcher forks them
        )
        self.conn: psycopg.Connection[Any] | None = None
        self.reads = 0  # the operator's reads of lot_status, to tell the cell's own commits from them

    def run(self) -> dict[str, Any]:
        try:
            self.say(
                f"starting a private cell: {self.n} machines with runs of 0 s"
                + (f", 2 with runs of {SLOW_RUN:g} s for the death trials" if self.slow else "")
            )
            self.cell.start()
            gid = lot_group(self.cell.cfg)
            if gid is not None:  # scripts of a user of their own read their plans here and write their timings
                soak = self.var / "soak"
                soak.mkdir(exist_ok=True)
                os.chown(soak, -1, gid)
                soak.chmod(0o2770)  # what is made in it is the lot user's group's
            self.conn = db.connect(self.cell.cfg, role="hi", log=self.log)
            self.conn.autocommit = True
            self.conn.execute(
                "INSERT INTO lot_scripts (script_id, path) VALUES (%s, %s) ON CONFLICT DO NOTHING",
                (SCRIPT_ID, SCRIPT_PATH),
            )
            self.conn.execute(
                "INSERT INTO products (product_id, script_id) VALUES (%s, %s) ON CONFLICT DO NOTHING",
                (PRODUCT, SCRIPT_ID),
            )
            result = self._lots()
            if self.solo:
                result.update(self._solo())
            if self.deaths:
                result["death_to_reroute_s"] = summary(self._death_trials())
            if self.freezes:
                result["freezes"] = freeze_trials(self, self.freezes)
            if self.idle_s > 0:
                result.update(self._idle())
            assert self.cell.bus is not None
            breaches = check_cell(self.cell.cfg, self.conn, self.cell.bus, settle=3.0)
            result["check_held"] = not breaches
            result["check_breaches"] = [f"{b.invariant}: {len(b.rows)} row(s)" for b in breaches]
            return result
        finally:
            if self.conn is not None:
                self.conn.close()
            self.cell.stop()

    # ----------------------------------------------------------------- lots

    def _order(self, alternatives: list[list[str]]) -> int:
        assert self.cell.bus is not None
        lot_id, entities = create_lot(self.cell.bus, PRODUCT, 1, owner="bench")
        plan_dir = self.cell.cfg.var / "soak"
        plan_dir.mkdir(parents=True, exist_ok=True)
        (plan_dir / f"lot-{lot_id}.json").write_text(json.dumps({"alternatives": alternatives}))
        spawn_lot_script(self.cell.cfg, entities[0])
        return entities[0]

    def operator(self, decided: set[tuple[int, str]], entities: list[int]) -> dict[int, str]:
        """Import and export what of `entities` waits; return their states. (Only theirs: the operator
        looks every 10 ms, and reading every lot's row would load the cell it measures.)"""
        assert self.conn is not None and self.cell.bus is not None
        self.reads += 1  # one transaction of its own (autocommit): not the cell's
        states = {
            int(e): str(s)
            for e, s in self.conn.execute(
                "SELECT entity_id, state FROM lot_status WHERE entity_id = ANY(%s)", (entities,)
            )
        }
        for e, s in states.items():
            action = {LotState.WAITING_IMPORT.value: "import", LotState.WAITING_EXPORT.value: "export"}.get(s)
            if action and (e, action) not in decided:
                try:
                    decide(self.cell.bus, e, action, "bench")
                    decided.add((e, action))
                except GwcError as err:  # not now: asked again at the next look
                    self.log.warning("%s of entity %d not taken: %s", action, e, err)
        return states

    def _lots(self) -> dict[str, Any]:
        self.say(f"running {self.m} lots, {self.at_once} at a time, each on the next free of {self.n} machines")
        # A lane holds one lot at a time; each new lot goes to the next machine no other lane uses, in turn,
        # so that with fewer lanes than machines every machine works and the cell's size is what grows.
        lane: dict[str, int | None] = {}
        turn = itertools.cycle(self.fast)
        ordered = finished = 0
        failed: list[int] = []
        decided: set[tuple[int, str]] = set()
        entities: list[int] = []
        cpu0, commits0, reads0 = self._cpu_by_role(), self._commits(), self.reads
        began = time.monotonic()
        last = began
        while finished < self.m:
            while len(lane) < self.at_once and ordered < self.m:
                m = next(x for x in turn if x not in lane)
                lane[m] = self._order([[m]])
                entities.append(lane[m])  # type: ignore[arg-type]
                ordered += 1
            states = self.operator(decided, [e for e in lane.values() if e is not None])
            for m, e in lane.items():
                if e is not None and states.get(e) in FINAL:
                    finished += 1
                    if states[e] == LotState.FAILED:
                        failed.append(e)
                    lane[m] = None
                    last = time.monotonic()
            lane = {m: e for m, e in lane.items() if e is not None}
            if time.monotonic() - last > LOT_TIMEOUT:
                raise GwcError(f"no lot finished for {LOT_TIMEOUT:.0f}s: see {self.cell.cfg.log_dir}")
            time.sleep(POLL)
        wall = last - began
        cpu1, commits1 = self._cpu_by_role(), self._commits() - (self.reads - reads0)
        overhead, parts = self._timings(entities)
        lot_cpu = [t["operate_cpu_s"] for t in self._timing_files(entities) if "operate_cpu_s" in t]
        cpu = {role: round((c - cpu0.get(role, 0.0)) * 1000 / self.m, 2) for role, c in sorted(cpu1.items())}
        if lot_cpu:
            cpu["lot (its operation)"] = round(sum(lot_cpu) * 1000 / len(lot_cpu), 2)
        return {
            "machines": self.n,
            "at_once": self.at_once,
            "lots": self.m,
            "failed": len(failed),
            "seconds": wall,
            "lots_per_s": self.m / wall if wall > 0 else float("nan"),
            "loaded_overhead_ms": summary(overhead),
            "loaded_phases_ms": parts,
            # where the time goes, counted: CPU per lot by process role while the lots ran, and commits
            "loaded_cpu_ms_per_lot": cpu,
            "db_commits_per_lot": round((commits1 - commits0) / self.m, 1),
            "script_cpu_ms": summary(script_cpu(self.cell.cfg.log_dir, entities)),
        }

    def _timing_files(self, entities: list[int]) -> list[dict[str, Any]]:
        """What each lot's script left about its operation (gwc/lot/scripts/soak.py)."""
        out = []
        for e in entities:
            try:
                out.append({"entity": e, **json.loads((self.cell.cfg.var / "soak" / f"timing-{e}.json").read_text())})
            except (OSError, ValueError):
                continue
        return out

    def _timings(self, entities: list[int]) -> tuple[list[float], dict[str, dict[str, float]]]:
        """Each lot's operation (request to unreserve, ms; lots that needed one try) and its phases."""
        overhead = [t["operate_s"] * 1000 for t in self._timing_files(entities) if t.get("tries") == 1]
        parts: dict[str, list[float]] = {}
        for timing in self._timing_files(entities):
            for k, v in phases(timing.get("events", [])).items():
                parts.setdefault(k, []).append(v * 1000)
        return overhead, {k: summary(v) for k, v in parts.items()}

    def _cpu_by_role(self) -> dict[str, float]:
        """CPU seconds so far of the cell's running processes, summed by role (all WCs together ...)."""
        # Lot scripts come and go (their operation's CPU is in their timing files): not counted here.
        # The agent forks them: their command line is the agent's, their name (comm) lot:E.
        roles = {pid: _role(cmd) for pid, cmd in self.cell.pids().items() if not _lot_script(pid, cmd)}
        database = self._database_pids()
        roles.update({pid: "database" for pid in database})
        out: dict[str, float] = {}
        for pid, role in roles.items():
            try:
                out[role] = out.get(role, 0.0) + cpu_s(pid)
            except OSError:
                continue
        if database:  # and the backends that ended (a lot script's connection, a probe's), reaped by the postmaster
            with contextlib.suppress(OSError):
                out["database"] = out.get("database", 0.0) + reaped_cpu_s(database[0])
        return out

    def _commits(self) -> int:
        """The database's transactions so far, as `counted` counts them (commits alone by default)."""
        assert self.conn is not None
        row = self.conn.execute(
            f"SELECT {self.counted} FROM pg_stat_database WHERE datname = current_database()"
        ).fetchone()
        return int(row[0]) if row else 0

    def _wait_states(
        self, entities: list[int], states: tuple[str, ...], decided: set[tuple[int, str]], what: str, poll: float = POLL
    ) -> dict[int, str]:
        deadline = Deadline(LOT_TIMEOUT)
        while True:
            now = self.operator(decided, entities)
            if all(now.get(e) in states for e in entities):
                return now
            if deadline.expired:
                raise GwcError(f"lots {entities} did not reach {what} within {LOT_TIMEOUT:.0f}s")
            time.sleep(poll)

    def _solo(self) -> dict[str, Any]:
        """The cell's own cost per lot: one lot at a time, its script already started and idle.

        Scripts are started a batch at a time and left waiting to be imported; then the operator
        imports one, waits for it to ask for export, exports it, and takes the next: while a lot
        operates, nothing else runs in the cell and no process starts.
        """
        self.say(f"running {self.solo} more lots one at a time (scripts started beforehand)")
        entities: list[int] = []
        failed = 0
        for start in range(0, self.solo, self.n):
            batch = [self._order([[m]]) for m in self.fast[: min(self.n, self.solo - start)]]
            entities += batch
            never: set[tuple[int, str]] = {(e, "import") for e in batch}  # parked: not imported yet
            self._wait_states(batch, (LotState.WAITING_IMPORT.value,), set(never), "waiting_import")
            for e in batch:
                decided = {x for x in never if x[0] != e}
                states = self._wait_states(
                    [e], (LotState.WAITING_EXPORT.value, LotState.FAILED.value), decided, "waiting_export", SOLO_POLL
                )
                failed += states[e] == LotState.FAILED
                self._wait_states([e], FINAL, decided, "exported")
        overhead, parts = self._timings(entities)
        return {"solo_lots": len(entities), "solo_failed": failed, "overhead_ms": summary(overhead), "phases_ms": parts}

    # ----------------------------------------------------------------- a resting cell

    def _idle(self) -> dict[str, Any]:
        """CPU the resting cell uses: every module and machine process, summed, in percent of one core,
        over `idle_s` seconds with no lot anywhere; the embedded database's processes apart. The cell
        is the N machines asked for: the death trials' two are stopped first."""
        if self.slow:
            self._stop_machines(self.slow)
        self.say(f"the cell of {self.n} machines at rest for {self.idle_s:g}s: CPU of all its processes")
        before = self._cpu_by_role()
        began = time.monotonic()
        time.sleep(self.idle_s)
        took = time.monotonic() - began
        after = self._cpu_by_role()
        percent = {role: 100 * (c - before.get(role, c)) / took for role, c in after.items()}
        beating = sum(1 for pid, cmd in self.cell.pids().items() if _role(cmd) != "me" and not _lot_script(pid, cmd))
        floor_s = min(self.idle_s, FLOOR_S)
        self.say(f"the floor: {beating} bare processes waking once a heartbeat, {floor_s:g}s")
        return {
            "idle_machines": self.n,
            "idle_floor_cpu_percent": round(wake_floor(beating, self.cell.cfg.bus.heartbeat, floor_s), 3),
            "idle_floor_processes": beating,
            "idle_s": round(took, 1),
            "idle_cpu_percent": round(sum(v for r, v in percent.items() if r != "database"), 3),
            "idle_cpu_percent_database": round(percent.get("database", 0.0), 3),
            "idle_cpu_percent_by_role": {r: round(v, 3) for r, v in sorted(percent.items())},
        }

    def _stop_machines(self, machines: list[str]) -> None:
        """Stop these machines' processes through the agent (off its watch: not restarted), and wait
        until the Machine Server has them Shutdown, so that the rest measured is the rest of the others."""
        self.say(f"stopping {', '.join(machines)}: the resting cell is the {self.n} machines asked for")
        names = [p.name for m in machines for p in reversed(machine_procs(self.cell.cfg, m))]  # the WC first
        agent_control.call(self.cell.cfg, "stop", names=names)
        assert self.conn is not None
        deadline = Deadline(LOT_TIMEOUT)
        query = "SELECT count(*) FROM machine_status WHERE machine_id = ANY(%s) AND status <> 'Shutdown'"
        while (row := self.conn.execute(query, (machines,)).fetchone()) and row[0]:
            if deadline.expired:
                raise GwcError(f"{', '.join(machines)} not Shutdown {LOT_TIMEOUT:.0f}s after their processes stopped")
            time.sleep(SOLO_POLL)

    def _database_pids(self) -> list[int]:
        """The embedded cluster's postmaster and its children (none for an outside database)."""
        if not self.cell.cfg.embedded:
            return []
        try:
            pm = int((self.cell.cfg.pg_dir / "postmaster.pid").read_text().split("\n", 1)[0])
            children = Path(f"/proc/{pm}/task/{pm}/children").read_text().split()
        except (OSError, ValueError):
            return []
        return [pm, *(int(c) for c in children)]

    # ----------------------------------------------------------------- deaths

    def _death_trials(self) -> list[float]:
        assert self.conn is not None
        self.say(f"{self.deaths} death trials: kill -9 the machine pair a lot runs on, time until it gets the other")
        times = []
        for k in range(self.deaths):
            entity, victim, deadline, decided = self.running_lot(f"death trial {k + 1}")
            other = next(m for m in self.slow if m != victim)
            killed_at = time.time()
            for p in machine_procs(self.cell.cfg, victim):
                self.cell.kill(p.name)
            # The lot finishes on the other machine; when it was given it, its timing file says (a BOUND event).
            while self.operator(decided, [entity]).get(entity) not in FINAL:
                if deadline.expired:
                    raise GwcError(f"death trial {k + 1}: entity {entity} did not finish")
                time.sleep(POLL * 5)
            (timing,) = self._timing_files([entity]) or [{}]
            rerouted = bound_to(timing.get("events", []), other, killed_at)
            if rerouted is None:
                raise GwcError(f"death trial {k + 1}: entity {entity} was not given {other} after {victim} died")
            times.append(rerouted - killed_at)
            self.say(f"  trial {k + 1}: {victim} killed, lot on {other} after {rerouted - killed_at:.2f}s")
            for p in machine_procs(self.cell.cfg, victim):
                self.cell.restart(p.name)
            self.machine_up(victim)
        return times

    def running_lot(self, what: str) -> tuple[int, str, Deadline, set[tuple[int, str]]]:
        """A lot ordered on either slow machine, once its run has started: (entity, its machine, the
        trial's deadline, the operator's decisions so far)."""
        assert self.conn is not None
        entity = self._order([[m] for m in self.slow])
        decided: set[tuple[int, str]] = set()
        deadline = Deadline(LOT_TIMEOUT)
        while True:
            self.operator(decided, [entity])
            row = self.conn.execute(
                "SELECT r.machine_id FROM reserved_machines r JOIN machine_status s USING (machine_id) "
                "WHERE r.entity_id = %s AND s.status = 'Running'",
                (entity,),
            ).fetchone()
            if row:
                return entity, str(row[0]), deadline, decided
            if deadline.expired:
                raise GwcError(f"{what}: the lot's run never started (entity {entity})")
            time.sleep(POLL)

    def machine_up(self, machine: str) -> None:
        """The killed machine back up (its WC resumes it or it needs ME_START), ready for the next trial."""
        assert self.conn is not None
        deadline = Deadline(LOT_TIMEOUT)
        while True:
            row = self.conn.execute("SELECT status FROM machine_status WHERE machine_id = %s", (machine,)).fetchone()
            if row and row[0] == "Idle":
                return
            if row and row[0] == "Shutdown":
                try:
                    self.cell.machine_start(machine, via_hi=False)
                except GwcError as e:
                    self.log.warning("%s would not start yet: %s", machine, e)
            if deadline.expired:
                raise GwcError(f"{machine} did not come back up")
            time.sleep(0.2)


def _role(cmd: str) -> str:
    """A process's role from its command line: the module of `gwc run X`, else what runs it."""
    if "gwc.lot.launcher" in cmd:  # the lot user's launcher (its forks, the scripts, are lot scripts)
        return "lot launcher"
    m = re.search(r"gwc (?:run (\S+)|(agent))", cmd)
    if m:
        return m.group(1) or m.group(2)
    return cmd.split(" ", 1)[0].rsplit("/", 1)[-1]


def wake_floor(processes: int, beat: float, seconds: float) -> float:
    """A resting cell's floor, in percent of one core: as many bare processes as the cell has bus members,
    at once, each only waking once a heartbeat for `seconds` (on a shared VM a wake-up's cost varies 4x)."""
    sleepers = [
        subprocess.Popen([sys.executable, "-c", _SLEEPER, str(beat), str(seconds)], stdout=subprocess.PIPE, text=True)
        for _ in range(processes)
    ]
    try:
        used = [float(p.communicate(timeout=seconds + 60)[0]) for p in sleepers]
    finally:  # one that failed or hung leaves none of the others behind
        for p in sleepers:
            if p.poll() is None:
                p.kill()
                p.wait()
    return 100 * sum(used) / seconds


def _lot_script(pid: int, cmd: str) -> bool:
    """Whether process `pid` is a lot script: exec'd (`python -m gwc.lot.run`), or forked by the agent or
    the lot launcher (named lot:E)."""
    try:
        return "gwc.lot.run" in cmd or Path(f"/proc/{pid}/comm").read_text().startswith("lot:")
    except OSError:
        return False


@click.command("cell")
@click.option("--machines", type=int, default=10, show_default=True, help="Dummy machines (runs take no time).")
@click.option("--lots", type=int, default=500, show_default=True, help="Lots to run.")
@click.option(
    "--solo",
    type=int,
    default=100,
    show_default=True,
    help="Then this many lots one at a time, for the cell's own cost per lot (0: skip).",
)
@click.option(
    "--deaths",
    type=int,
    default=3,
    show_default=True,
    help="Death trials (0: none): kill the machine a lot runs on, time until it has the alternative.",
)
@click.option(
    "--dir",
    "where",
    type=click.Path(file_okay=False, path_type=Path),
    help="The private cell's folder (default: var/bench-cell); emptied first.",
)
@click.option(
    "--kernel-filter/--no-kernel-filter",
    default=True,
    show_default=True,
    help="The bus's kernel filter (docs/protocol.md): off shows what it saves.",
)
@click.option(
    "--freezes",
    type=int,
    default=0,
    show_default=True,
    help="Freeze trials (gwc/bench/heal.py): SIGSTOP a running machine's WC for 8 s, count runs done twice.",
)
@click.option(
    "--idle",
    "idle_s",
    type=float,
    default=60.0,
    show_default=True,
    help="Then seconds of rest: the CPU the resting cell uses (0: skip).",
)
@click.option(
    "--at-once",
    type=int,
    default=0,
    show_default=True,
    help="Lots at work at a time, each on the next free machine in turn (0: one per machine).",
)
@click.option(
    "--history/--no-history",
    default=True,
    show_default=True,
    help="The production record ([record] history, docs/record.md): off shows what writing it costs.",
)
@click.option(
    "--compare-history",
    "compare",
    type=int,
    default=0,
    help="Instead: N pairs of lot runs, history off then on (then on, off: the order alternates), side by side.",
)
@click.option(
    "--lot-user",
    default="",
    help="Lot scripts run as this OS user ([lots] user; run the bench as root, --dir where that user can "
    "reach): its launcher forks them, or, with --no-launcher, each is exec'd. Default: as the bench's user.",
)
@click.option(
    "--launcher/--no-launcher",
    default=True,
    show_default=True,
    help="With --lot-user: scripts forked by the lot user's launcher, or each exec'd ([lots] launcher).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def command(
    machines: int,
    lots: int,
    solo: int,
    deaths: int,
    where: Path | None,
    kernel_filter: bool,
    freezes: int,
    idle_s: float,
    at_once: int,
    history: bool,
    compare: int,
    lot_user: str,
    launcher: bool,
    as_json: bool,
) -> None:
    """Run lots through a private cell of N dummy machines: lots/s, the cell's overhead per lot
    (machine request to unreserve, median and p99) and the time from a machine's death to the
    first lot served by its alternative. Uses $GWC_DATABASE_URL if set, else an embedded cluster
    of its own."""
    if machines < 1 or lots < 1 or solo < 0 or deaths < 0 or freezes < 0:
        raise click.BadParameter("--machines and --lots must be at least 1, --solo and --deaths at least 0")
    cfg, log = bench_context(caps=AGENT_CAPS if lot_user else ())  # its agent starts scripts as lot_user
    if compare > 0:
        from gwc.bench.history import compare_history

        return compare_history(
            CellBench, cfg.var / "bench-cell" if where is None else where, machines, lots, compare, as_json
        )
    bench = CellBench(
        where or cfg.var / "bench-cell",
        machines,
        lots,
        solo,
        deaths,
        os.environ.get("GWC_DATABASE_URL"),
        log,
        (lambda s: None) if as_json else click.echo,
        kernel_filter,
        freezes,
        idle_s,
        at_once,
        history,
        {"user": lot_user, "launcher": launcher} if lot_user else None,
    )
    result = bench.run()
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(
        f"{result['lots']} lots on {result['machines']} machines in {result['seconds']:.1f}s: "
        f"{result['lots_per_s']:.2f} lots/s ({result['failed']} failed)"
    )
    click.echo(
        f"  overhead per lot with {result['at_once']} lots at once, request to unreserve (ms): "
        f"{brief(result['loaded_overhead_ms'])}"
    )
    for k, v in result["loaded_phases_ms"].items():
        click.echo(f"    {k:22s} (ms): {brief(v)}")
    click.echo(
        f"  per lot: {result['db_commits_per_lot']} database commits; CPU (ms) "
        + ", ".join(f"{k} {v}" for k, v in result["loaded_cpu_ms_per_lot"].items())
    )
    click.echo(f"  a lot script's whole CPU, start-up included (ms): {brief(result['script_cpu_ms'])}")
    if "overhead_ms" in result:
        click.echo(
            f"overhead per lot, one lot at a time, request to unreserve (ms): {brief(result['overhead_ms'])} "
            f"({result['solo_failed']} failed)"
        )
        for k, v in result["phases_ms"].items():
            click.echo(f"    {k:22s} (ms): {brief(v)}")
    if "death_to_reroute_s" in result:
        click.echo(f"death to reroute (s): {brief(result['death_to_reroute_s'])}")
    if "freezes" in result:
        f = result["freezes"]
        click.echo(
            f"WC frozen {f['freeze_s']:g}s mid-run, {f['trials']} trials: "
            f"runs done twice {f['runs_done_twice']}, lots {f['lots']}"
        )
    if "idle_cpu_percent" in result:
        click.echo(
            f"the cell at rest ({result['idle_s']:g}s): {result['idle_cpu_percent']:.2f}% of one core "
            f"(the database: {result['idle_cpu_percent_database']:.2f}%): "
            + ", ".join(f"{k} {v:.2f}" for k, v in result["idle_cpu_percent_by_role"].items())
            + f"; the floor ({result['idle_floor_processes']} bare processes waking once a heartbeat): "
            f"{result['idle_floor_cpu_percent']:.2f}%"
        )
    click.echo(
        "gwc check at the end: "
        + ("held" if result["check_held"] else "BROKEN: " + "; ".join(result["check_breaches"]))
    )
