"""`gwc bench failover`: how long production stops when the active servers' host dies (issue 36).

A private cell (gwc/soak/cell.py, with its agent) whose servers and MSCHED are leased (gwc/lease.py),
each with one standby, runs a steady stream of lots on dummy machines. Each trial kills -9 every
active instance at once (the processes of the active "host": on one machine, the lease holders) and
measures the time from the kill to the next machine bound (a machine_run_id newer than any before
the kill) and to the next run set up (that newer run in Setup, Running, or done). The agent starts the killed
instances again, standbys now; the bench keeps a second instance of each server running. At the
end: the lots lost (ordered, neither exported nor failed with a reason), the lots that ran their
operation twice and the committed rows lost (lot_status rows of ordered entities that are gone).

One host: the network cut and a dead host's TCP sessions (the fenced, 'expired' takeover, a ttl
later) are measured by tests/e2e/test_failover.py on namespace hosts (docs/reliability.md).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import psycopg

from gwc import db
from gwc.bench import summary
from gwc.client.orders import decide
from gwc.client.session import bench_context
from gwc.config import SERVER_MODULES, dump_toml, load_config
from gwc.errors import GwcError
from gwc.ipc.codes import LotState
from gwc.lot.entity import create_lot
from gwc.lot.model import read_traveller
from gwc.lot.run import spawn_lot_script
from gwc.retry import Deadline
from gwc.soak.cell import PrivateCell
from gwc.soak.driver import PRODUCT, SCRIPT_ID, SCRIPT_PATH

MACHINES = ("wc1", "wc2", "wc3")
RUN_S = 0.3
IN_FLIGHT = 3  # lots at work at a time
SETTLE_S = 2.0  # after a trial, before the next kill: the standbys are back and waiting
REDECIDE_S = 5.0  # an import/export asked and not done is asked again after this long
BAR_S = 30.0  # a trial whose production did not resume within this is counted at this


class FailoverBench:
    def __init__(
        self, var: Path, trials: int, database_url: str | None, log: logging.Logger, say: Callable[[str], None]
    ):
        self.trials = trials
        self.log = log
        self.say = say
        if var.exists():
            shutil.rmtree(var)
        specs = [{"id": m, "kind": "dummy", "run_time": RUN_S} for m in MACHINES]
        self.cell = PrivateCell(var, specs, log, database_url, agent=True)
        doc = tomllib.loads(self.cell.cfg.path.read_text())
        doc["module"] = [{"name": m, "lease": True} for m in SERVER_MODULES]
        doc["lease"] = {"ttl": 3.0, "poll": 0.1}
        self.cell.cfg.path.write_text(dump_toml(doc))
        self.cell.cfg = dataclasses.replace(load_config(self.cell.cfg.path), var=self.cell.var)
        self.standbys: dict[str, subprocess.Popen[bytes]] = {}
        self.conn: psycopg.Connection[Any] | None = None
        self.entities: list[int] = []
        self.decided: dict[tuple[int, str], float] = {}  # (entity, import/export) -> when asked

    # ----------------------------------------------------------------- the cell

    def _standby(self, name: str) -> None:
        """A second instance of the module, started by hand (the agent runs one of each on one host)."""
        p = self.standbys.get(name)
        if p is not None and p.poll() is None:
            return
        out = open(self.cell.cfg.log_dir / f"standby-{name}.out", "ab")  # noqa: SIM115
        self.standbys[name] = subprocess.Popen(
            [sys.executable, "-m", "gwc", "run", name],
            env=self.cell.env(),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        out.close()

    def _query(self, text: str, *args: Any) -> list[tuple[Any, ...]]:
        assert self.conn is not None
        cur = self.conn.execute(text, args)
        return cur.fetchall() if cur.description is not None else []

    def _holders(self) -> dict[str, tuple[int, int]]:
        """module -> (epoch, pid of its active instance)."""
        return {
            str(n): (int(e), int(str(h).split(":")[1]))
            for n, e, h in self._query("select name, epoch, holder from module_leases")
        }

    def _standing_by(self) -> bool:
        """Every module has an instance besides its active one connected, waiting for the lease: two
        sessions under its role (a standby polls on its own). The agent restarts a killed instance
        after a backoff that grows with its kills in a row, so a trial waits for it."""
        sessions = dict(
            self._query(
                "select application_name, count(*) from pg_stat_activity where application_name = any(%s) group by 1",
                [f"gwc_{m}" for m in SERVER_MODULES],
            )
        )
        return all(p.poll() is None for p in self.standbys.values()) and all(
            sessions.get(f"gwc_{m}", 0) >= 2 for m in SERVER_MODULES
        )

    # ----------------------------------------------------------------- lots

    def _order(self) -> None:
        assert self.cell.bus is not None
        lot_id, entities = create_lot(self.cell.bus, PRODUCT, 1, owner="bench")
        plan_dir = self.cell.cfg.var / "soak"
        plan_dir.mkdir(parents=True, exist_ok=True)
        (plan_dir / f"lot-{lot_id}.json").write_text(json.dumps({"alternatives": [list(MACHINES)]}))
        spawn_lot_script(self.cell.cfg, entities[0])
        self.entities.append(entities[0])

    def _operate(self, order: bool = True) -> dict[int, str]:
        """The operator: import and export what waits (asked again after REDECIDE_S, should a server
        taking over have lost it) and, if `order`, keep IN_FLIGHT lots at work. The lots' states."""
        assert self.cell.bus is not None
        states = {
            int(e): str(s)
            for e, s in self._query("select entity_id, state from lot_status where entity_id = any(%s)", self.entities)
        }
        now = time.monotonic()
        for e, s in states.items():
            action = {LotState.WAITING_IMPORT.value: "import", LotState.WAITING_EXPORT.value: "export"}.get(s)
            if action and now - self.decided.get((e, action), -REDECIDE_S) >= REDECIDE_S:
                try:
                    decide(self.cell.bus, e, action, "bench")
                    self.decided[(e, action)] = now
                except GwcError as err:  # a server taking over: asked again at the next look
                    self.log.info("%s of entity %d not taken now: %s", action, e, err)
        at_work = sum(1 for e in self.entities if states.get(e) not in ("exported", "failed"))
        for _ in range(IN_FLIGHT - at_work if order else 0):
            try:
                self._order()
            except GwcError as err:
                self.log.info("a lot not ordered now: %s", err)
        return states

    def _last_binding(self) -> int:
        return int(
            self._query(
                "select greatest((select max(machine_run_id) from reserved_machines), "
                "(select max(machine_run_id) from machine_run_outcome), 0)"
            )[0][0]
        )

    def _set_up_after(self, before: int) -> bool:
        """A run bound after the kill was set up: its machine in Setup or Running with it, or its outcome
        stored (a run of 0.3 s may be over between two looks)."""
        return bool(
            self._query(
                "select 1 from machine_status where status in ('Setup', 'Running') and machine_run_id > %s "
                "union all select 1 from machine_run_outcome where machine_run_id > %s limit 1",
                before,
                before,
            )
        )

    # ----------------------------------------------------------------- trials

    def _trial(self, n: int) -> tuple[float, float]:
        deadline = Deadline(60)
        while not self._standing_by() or self._last_binding() == 0:
            self._operate()
            for name in SERVER_MODULES:
                self._standby(name)
            if deadline.expired:
                raise GwcError("the standbys did not come up within 60 s")
            time.sleep(0.1)
        time.sleep(SETTLE_S)
        for _ in range(20):  # a moment of steady production before the kill
            self._operate()
            time.sleep(0.05)
        before = self._last_binding()
        holders = self._holders()
        killed = time.monotonic()
        for _, pid in holders.values():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        bound = setup = 0.0
        while time.monotonic() - killed < BAR_S and not (bound and setup):
            if not bound and self._last_binding() > before:
                bound = time.monotonic() - killed
            if not setup and self._set_up_after(before):
                setup = time.monotonic() - killed
            self._operate()
            time.sleep(0.02)
        bound, setup = bound or BAR_S, setup or BAR_S
        self.say(f"trial {n}: next machine bound {bound:.2f}s, next run set up {setup:.2f}s after the kill")
        return bound, setup

    def run(self) -> dict[str, Any]:
        self.say(f"starting a private cell with a standby of each server, {len(MACHINES)} machines")
        try:
            self.cell.start()
            self.conn = db.connect(self.cell.cfg, role="hi", log=self.log)
            self.conn.autocommit = True
            self._query(
                "insert into lot_scripts (script_id, path) values (%s, %s) on conflict do nothing",
                SCRIPT_ID,
                SCRIPT_PATH,
            )
            self._query(
                "insert into products (product_id, script_id) values (%s, %s) on conflict do nothing",
                PRODUCT,
                SCRIPT_ID,
            )
            bound: list[float] = []
            setup: list[float] = []
            for n in range(1, self.trials + 1):
                b, s = self._trial(n)
                bound.append(b)
                setup.append(s)
            deadline = Deadline(120)
            while not deadline.expired:
                states = self._operate(order=False)
                if all(s in ("exported", "failed") for s in states.values()) and len(states) == len(self.entities):
                    break
                time.sleep(0.2)
            return self._account(bound, setup)
        finally:
            for p in self.standbys.values():
                if p.poll() is None:
                    p.terminate()
            for p in self.standbys.values():
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
            if self.conn is not None:
                self.conn.close()
            self.cell.stop()

    def _account(self, bound: list[float], setup: list[float]) -> dict[str, Any]:
        rows = dict(self._query("select entity_id, state from lot_status where entity_id = any(%s)", self.entities))
        failed = dict(
            self._query(
                "select entity_id, reason from lot_status where state = 'failed' and entity_id = any(%s)", self.entities
            )
        )
        lost = [
            e for e in self.entities if rows.get(e) not in ("exported", "failed") or (e in failed and not failed[e])
        ]
        # Run twice (as the soak judges it): an entity with two operations done (a soak lot has one), or
        # a machine_run_id given to two entities.
        twice = 0
        owner: dict[int, int] = {}
        for e in self.entities:
            steps = (read_traveller(self.cell.cfg, e) or {}).get("steps", [])
            twice += len([st for st in steps if st.get("runs")]) > 1
            for st in steps:
                twice += owner.setdefault(int(st["machine_run_id"]), e) != e
        resume = summary(bound)
        return {
            "trials": self.trials,
            "resume_s": {"median": resume["median"], "p99": resume["p99"], "max": resume["max"]},
            "setup_s": {k: summary(setup)[k] for k in ("median", "p99", "max")},
            "lots": len(self.entities),
            "lots_failed": len(failed),
            "lots_lost": len(lost),
            "runs_twice": twice,
            "rows_lost": len([e for e in self.entities if e not in rows]),
        }


@click.command("failover")
@click.option("--trials", type=int, default=10, show_default=True, help="Kills of the active servers.")
@click.option("--dir", "where", type=click.Path(path_type=Path), default=None, help="The private cell's folder.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def command(trials: int, where: Path | None, as_json: bool) -> None:
    """Kill every active server and MSCHED at once, TRIALS times, while lots run: the time from the kill
    to the next machine bound and to the next run set up, lots lost or run twice. Uses
    $GWC_DATABASE_URL if set, else an embedded cluster of its own."""
    if trials < 1:
        raise click.BadParameter("--trials must be at least 1")
    cfg, log = bench_context()
    bench = FailoverBench(
        where or cfg.var / "bench-failover",
        trials,
        os.environ.get("GWC_DATABASE_URL"),
        log,
        (lambda s: None) if as_json else click.echo,
    )
    result = bench.run()
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    r, s = result["resume_s"], result["setup_s"]
    click.echo(
        f"{result['trials']} trials: next machine bound median {r['median']:.2f}s, p99 {r['p99']:.2f}s, "
        f"max {r['max']:.2f}s; next run set up median {s['median']:.2f}s, p99 {s['p99']:.2f}s"
    )
    click.echo(
        f"{result['lots']} lots: {result['lots_failed']} failed, {result['lots_lost']} lost, "
        f"{result['runs_twice']} run twice, {result['rows_lost']} rows lost"
    )
