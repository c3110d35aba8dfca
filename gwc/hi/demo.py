"""`gwc demo`: the thesis's section 7 demonstration in one command.

On its own cell (etc/demo.toml: state in var/demo, its own bus port and embedded database, so it
never disturbs a cell run from etc/cell.toml) it does what 7.4 did by hand: starts the database and
every module, starts the CMM (simulated over a pseudo-terminal: the operator pushes its start
button, i.e. clears the HOME_CMM alarm) and the Mazak, enters a work order for a chess set
(aluminium sets measured on the CMM, pawns milled then measured), imports the lots as they ask, lets
MSCHED share the machines among them, starts another mill and stops the Mazak while lots run,
exports the finished lots, prints each lot's result and the machine run results, and stops the
cell. It prints what happens as it happens and exits 0 only if every lot finished as expected.

The operator's part (import, export, the CMM's start button) is played by a thread of this command
through the same conversations the `gwc import`, `gwc export` and `gwc alarm clear` commands hold.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import psycopg
from psycopg import sql

from gwc import cell, db
from gwc.check import check_database
from gwc.client.alarms import clear_alarm, read_status_line
from gwc.client.machines import start_machine, stop_machine
from gwc.client.orders import decide, enter_order, read_traveller
from gwc.client.session import hi_bus
from gwc.config import Config, load_config, shipped
from gwc.errors import GwcError
from gwc.hostuser import AGENT_CAPS, become_cell_user
from gwc.ipc import BlockingBus, keys
from gwc.ipc.codes import LotState
from gwc.log import open_log
from gwc.record import store
from gwc.retry import Deadline

DEMO_CONFIG = shipped("etc") / "demo.toml"
BY = "demo operator"
POLL = 0.1
FINAL = (LotState.EXPORTED, LotState.FAILED)


class Demo:
    """One run of the demonstration: the cell, the operator thread, the narration."""

    def __init__(self, cfg: Config, say: Callable[[str], None], chess: int, pawns: int, timeout: float) -> None:
        self.cfg = cfg
        self.log = open_log("demo", cfg.log_dir, "note")
        self.say_raw = say
        self.chess = chess
        self.pawns = pawns
        self.timeout = timeout
        self.t0 = time.monotonic()
        self.bus: BlockingBus | None = None
        self.stop_watch = threading.Event()
        self.lock = threading.Lock()
        self.states: dict[int, str] = {}
        self.machines: dict[str, tuple[str, Any]] = {}
        self.cleared: set[int] = set()
        self.errors: list[str] = []

    def say(self, text: str) -> None:
        with self.lock:
            self.say_raw(f"[{time.monotonic() - self.t0:6.1f}s] {text}")

    # ----------------------------------------------------------------- the run

    def run(self, keep: bool) -> bool:
        cfg = self.cfg
        self.say(f"GWC demonstration (thesis section 7) on cell {cfg.cell_name}: config {cfg.path}, state {cfg.var}")
        if keys.ensure(cfg.bus):  # the demonstration's cell is its own: fresh state makes its keys (gwc key new)
            self.say(f"bus: new keys for the demonstration's cell in {keys.key_files(cfg.bus)[0].parent}")
        self.say("stopping anything left from an earlier demonstration")
        cell.stop_cell(cfg, self.log, say=lambda s: None, database=False)
        self._bus_is_free()
        if cfg.embedded:
            db.cluster_start(cfg, self.log)
            self._fresh_database()
            self.say("database: embedded PostgreSQL cluster running, fresh database 'gwc'")
        try:
            cell.start_cell(cfg, self.log, say=lambda s: self.say(f"start: {s}"))
            self.bus = hi_bus(cfg, self.log)
            watcher = threading.Thread(target=self._watch, name="demo-operator", daemon=True)
            watcher.start()
            ok = self._production()
        finally:
            self.stop_watch.set()
            if self.bus is not None:
                self.bus.close()
            if keep:
                self.say(f"leaving the cell running (--keep): stop it with `GWC_CONFIG={cfg.path} gwc stop`")
            else:
                self.say("stopping the cell")
                cell.stop_cell(cfg, self.log, say=lambda s: self.say(f"stop: {s}"))
        return ok

    def _bus_is_free(self) -> None:
        """Another cell on this bus group and port would answer for ours: refuse to mix with it."""
        with hi_bus(self.cfg, self.log) as bus:
            time.sleep(self.cfg.bus.heartbeat * 2)  # a window for hellos, not a wait for a condition
            others = sorted(p for p in bus.peers() if not p.startswith("hi."))
        if others:
            raise GwcError(
                f"another cell is running on bus {self.cfg.bus.group}:{self.cfg.bus.port} "
                f"({', '.join(others[:6])}): stop it, or give the demonstration another [bus] port "
                f"in {self.cfg.path}"
            )

    def _fresh_database(self) -> None:
        """The demo's own cluster gets a new database each run, so every run starts from the seed."""
        url = db.database_url(self.cfg).replace(f"@/{db.DB_NAME}?", "@/postgres?", 1)
        with psycopg.connect(url, autocommit=True) as conn:
            conn.execute(sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(db.DB_NAME)))
            conn.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(db.DB_NAME)))
        # The travellers of an earlier run belong to its database: gone with it. (A traveller another
        # user wrote, e.g. the cell's before its lot scripts had a user of their own, could not be
        # replaced by a script of the lot user in var/lots, which is sticky: it would be resumed.)
        for old in (self.cfg.var / "lots").glob("entity-*.json"):
            old.unlink(missing_ok=True)

    def _production(self) -> bool:
        assert self.bus is not None
        machines = [m.id for m in self.cfg.machines]
        mills = [m for m in machines if m != "cmm_wc"]
        first_mill, spare_mill = mills[0], mills[1]
        for mid in ("cmm_wc", first_mill):
            self.say(f"operator: start machine {mid}")
            self.say(f"machine {mid}: {start_machine(self.cfg, self.bus, mid, timeout=60)}")
        items = [(p, n) for p, n in (("alum_chess_set", self.chess), ("milled_pawn", self.pawns)) if n]
        self.say("operator: work order entry (WOEN) for NJIT: " + ", ".join(f"{n} x {p}" for p, n in items))
        order = enter_order(self.cfg, self.log, self.bus, "NJIT", items, note="section 7 demonstration")
        entities = [e for lot in order["lots"] for e in lot["entities"]]
        for lot in order["lots"]:
            self.say(
                f"work order {order['work_order_id']}: lot {lot['lot_id']} of {lot['quantity']} "
                f"{lot['product_id']}, entities {', '.join(map(str, lot['entities']))}, one lot script each"
            )
        deadline = Deadline(self.timeout)
        # While lots run: once the first mill has done a run, a second mill joins and the first leaves.
        if self.pawns:
            self._wait(
                lambda: self.machines.get(first_mill, ("",))[0] == "Running" or self._runs_on(first_mill) > 0,
                deadline,
                f"a run on {first_mill}",
            )
            self.say(f"operator: start machine {spare_mill} while lots run")
            self.say(f"machine {spare_mill}: {start_machine(self.cfg, self.bus, spare_mill, timeout=60)}")
            self.say(f"operator: stop machine {first_mill} while lots run")
            done = stop_machine(self.cfg, self.bus, first_mill, timeout=60)
            self.say(f"machine {first_mill}: {done} (a machine in a run finishes it first)")
        self._wait(lambda: all(self.states.get(e) in FINAL for e in entities), deadline, "every lot to be exported")
        return self._report(entities)

    def _wait(self, predicate: Callable[[], bool], deadline: Deadline, what: str) -> None:
        while not predicate():
            if self.errors:
                raise GwcError(f"demonstration failed: {self.errors[0]}")
            if deadline.expired:
                raise GwcError(f"demonstration timed out waiting for {what} (logs in {self.cfg.log_dir})")
            time.sleep(POLL)

    # ----------------------------------------------------------------- the operator and the narrator

    def _watch(self) -> None:
        """Thread: narrate lot and machine changes; import, export and push the CMM's start button."""
        try:
            with db.connect(self.cfg, role="hi", log=self.log) as conn:
                while not self.stop_watch.is_set():
                    self._look(conn)
                    conn.rollback()
                    self.stop_watch.wait(POLL)
        except Exception as e:  # the main thread reports it and stops
            self.log.exception("demo operator failed")
            self.errors.append(f"operator thread: {e}")

    def _look(self, conn: psycopg.Connection[Any]) -> None:
        assert self.bus is not None
        for alarm_no, alarm_id, machine_id, text in conn.execute(
            "SELECT alarm_no, alarm_id, machine_id, alarm_text FROM alarms WHERE cleared_at IS NULL ORDER BY alarm_no"
        ).fetchall():
            if alarm_no in self.cleared:
                continue
            self.cleared.add(alarm_no)
            self.say(f"alarm {alarm_no} {alarm_id} on {machine_id or '-'}: {text}")
            if alarm_id == "HOME_CMM":
                self.say(f"operator: pushes the start button on the CMM (clears alarm {alarm_no})")
                try:
                    clear_alarm(self.bus, alarm_no, BY)
                except GwcError as e:
                    self.errors.append(f"alarm {alarm_no} could not be cleared: {e}")
        for mid, status, run_id, recipe in conn.execute(
            "SELECT machine_id, status, machine_run_id, recipe_id FROM machine_status "
            "WHERE machine_id = ANY(%s) ORDER BY 1",
            ([m.id for m in self.cfg.machines],),
        ).fetchall():
            if self.machines.get(mid, (None, None))[0] != status:
                what = f" (run {run_id}, recipe {recipe})" if status in ("Setup", "Running") else ""
                if mid in self.machines or status != "Shutdown":
                    self.say(f"machine {mid}: {status}{what}")
            self.machines[mid] = (status, run_id)
        line_read = False
        for entity, lot, product, state, reason in conn.execute(
            "SELECT s.entity_id, s.lot_id, l.product_id, s.state, s.reason FROM lot_status s "
            "JOIN lots l USING (lot_id) ORDER BY s.entity_id"
        ).fetchall():
            if self.states.get(entity) == state:
                continue
            self.states[entity] = state
            extra = f": {reason}" if reason and state in ("completed", "failed") else ""
            self.say(f"lot entity {entity} ({product}, lot {lot}): {state}{extra}")
            if state in ("waiting_import", "waiting_export"):
                if not line_read:
                    line_read = True
                    self.say(f"status line: {self._status_line()}")
                action = "import" if state == "waiting_import" else "export"
                self.say(f"operator: {action} entity {entity} ({'IMPL' if action == 'import' else 'export'})")
                try:
                    decide(self.bus, entity, action, BY)
                except GwcError as e:
                    self.errors.append(str(e))

    def _status_line(self) -> str:
        """What the Status Line Server shows the operator now (STATUS_LN)."""
        assert self.bus is not None
        try:
            return str(read_status_line(self.bus, timeout=3).text)
        except GwcError as e:
            return f"(not available: {e})"

    # ----------------------------------------------------------------- the results

    def _runs_on(self, machine_id: str) -> int:
        with db.connect(self.cfg, role="hi", log=self.log) as conn:
            row = conn.execute(
                "SELECT count(DISTINCT machine_run_id) FROM machine_run_result WHERE machine_id = %s", (machine_id,)
            ).fetchone()
        return int(row[0]) if row else 0

    def _traced(self, entity: int, trav: dict[str, Any], traced: dict[str, Any] | None) -> list[str]:
        """The production record's genealogy of the entity (`gwc trace entity`) against its traveller:
        the same runs, on the same machines, in the same order."""
        want = [(m, s["machine_run_id"]) for s in trav.get("steps", []) for m in sorted(s["machines"])]
        got = [(s["machine_id"], s["machine_run_id"]) for s in (traced or {}).get("steps", [])]
        # one run on several machines: their Running rows may come in either order
        if sorted(got) == sorted(want) and [r for _, r in got] == [r for _, r in want]:
            self.say(f"      trace: {len(got)} runs, as the traveller says")
            return []
        return [f"entity {entity}: gwc trace entity lists {got}, its traveller {want}"]

    def _report(self, entities: list[int]) -> bool:
        problems: list[str] = []
        with db.connect(self.cfg, role="hi", log=self.log) as conn:
            lots = conn.execute(
                "SELECT s.entity_id, l.product_id, s.state, s.reason FROM lot_status s "
                "JOIN lots l USING (lot_id) WHERE s.entity_id = ANY(%s) ORDER BY 1",
                (entities,),
            ).fetchall()
            runs = conn.execute(
                "SELECT machine_run_id, machine_id, string_agg(param || '=' || coalesce(value, ''), "
                "' ' ORDER BY param), min(recorded_at) FROM machine_run_result "
                "GROUP BY machine_run_id, machine_id ORDER BY 1"
            ).fetchall()
            breaches = check_database(conn)
            traces = {e: store.trace_entity(conn, e) for e, *_ in lots}
            on_wc2 = {w["entity_id"] for w in store.trace_where(conn, machine_id="wc2")}
        self.say("results of each lot:")
        for entity, product, state, reason in lots:
            trav = read_traveller(self.cfg, entity) or {}
            path = " -> ".join(
                f"{s['op_type']}@{','.join(s['machines'])}#{s['machine_run_id']}" for s in trav.get("steps", [])
            )
            self.say(f"  entity {entity:>3} {product:<15} {state:<9} {reason or ''}")
            if path:
                self.say(f"      runs: {path}")
            problems += self._traced(entity, trav, traces.get(entity))
            if state != LotState.EXPORTED:
                problems.append(f"entity {entity} is {state}: {reason}")
            elif not reason or reason.split(":")[0].split()[0] not in ("PASS", "FAIL", "SCRAP"):
                problems.append(f"entity {entity} has no result")
        travelled = {
            e for e, *_ in lots for s in (read_traveller(self.cfg, e) or {}).get("steps", []) if "wc2" in s["machines"]
        }
        if on_wc2 == travelled:
            self.say(f"trace where --machine wc2: entities {sorted(on_wc2)}, as their travellers say")
        else:
            problems.append(f"trace where --machine wc2 lists {sorted(on_wc2)}, travellers say {sorted(travelled)}")
        self.say("machine run results (MACHINE_RUN_RESULT):")
        for run_id, mid, results, _ in runs:
            self.say(f"  run {run_id:>3} on {mid:<7} {results}")
        if not runs:
            problems.append("no run results in MACHINE_RUN_RESULT")
        for b in breaches:
            problems.append(f"invariant {b.invariant} breached: {b.promise}")
        if problems:
            for p in problems:
                self.say(f"PROBLEM: {p}")
            self.say("demonstration FAILED")
            return False
        self.say(
            f"demonstration succeeded: {len(entities)} lots exported, {len(runs)} machine runs, every invariant holds"
        )
        return True


@click.command("demo")
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=DEMO_CONFIG,
    show_default=True,
    help="The demonstration cell's configuration.",
)
@click.option("--chess", default=2, show_default=True, help="Aluminium chess sets to order (measured on the CMM).")
@click.option(
    "--pawns",
    default=3,
    show_default=True,
    help="Pawns to order (milled, then measured; re-milled if out of tolerance).",
)
@click.option("--timeout", default=100.0, show_default=True, help="Seconds the lots may take in all.")
@click.option("--keep", is_flag=True, help="Leave the cell running at the end (to look around with gwc commands).")
@click.option(
    "--console",
    "with_console",
    is_flag=True,
    help="Watch it live in the operator's console (`gwc console`; the narration is its Demo tab, 9).",
)
def demo(config_path: Path, chess: int, pawns: int, timeout: float, keep: bool, with_console: bool) -> None:
    """Run section 7's demonstration: start a cell, order a chess set, run it, print the results, stop.

    Exits 0 only if every lot was exported with its result. Runs on its own cell (etc/demo.toml,
    state in var/demo, embedded database), in about a minute.
    """
    if chess < 0 or pawns < 0 or chess + pawns == 0:
        raise GwcError("order at least one chess set or pawn (--chess N, --pawns N)")
    cfg = load_config(config_path)
    become_cell_user(cfg, AGENT_CAPS)  # as root: the cell's user, keeping what its agent needs (gwc.hostuser)
    mills = [m.id for m in cfg.machines if m.kind == "dummy"]
    if not any(m.id == "cmm_wc" for m in cfg.machines) or len(mills) < 2:
        raise GwcError(f"{config_path}: the demonstration needs machine cmm_wc and two dummy machines")
    if with_console:
        from gwc.console.app import run_beside  # Textual only when asked for

        keys.ensure(cfg.bus)  # the console joins the bus before the demonstration would make its keys
        ok = run_beside(cfg, lambda say: Demo(cfg, say, chess, pawns, timeout).run(keep), click.echo)
    else:
        ok = Demo(cfg, click.echo, chess, pawns, timeout).run(keep)
    if not ok:
        raise click.exceptions.Exit(1)


commands = [demo]
