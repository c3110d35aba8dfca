"""The chaos soak: a whole cell runs a seeded stream of lots while a seeded driver breaks it.

One loop, one thread (plus the observer's bus), doing in turn what three people would:

* the order desk: creates the plan's lots when they are due (never more than `max_active`
  unfinished at once), writes each lot's plan for its script and starts the script;
* the operator: imports and exports the lots that wait for it, starts machines that are down
  (through the Human Interface, `gwc machine start`) unless a fault holds them down;
* the chaos driver: at the plan's moments, kill -9 a WC, an ME, a machine pair, MSCHED or a
  server, stops a machine through the HI, restarts a process with the bus fault injector on, or
  kills a lot script; after the fault's downtime it repairs it. Faults come one at a time, in the
  plan's order, so the same seed gives the same sequence of faults.

Every fault and repair is appended to <soak>/actions.jsonl, headed by the plan's seed and options,
so `gwc soak --replay <soak>/actions.jsonl` runs the same scenario again. At the end the driver
repairs everything, waits for every lot to finish, checks the invariants (gwc.check), accounts
for every lot (finished or failed with a reason, none lost, none run twice), stops the cell and
lists whatever it left behind.
"""

from __future__ import annotations

import json
import logging
import random
import shutil
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import psycopg

from gwc import db
from gwc.cell import cell_procs, machine_procs, start_procs
from gwc.check import check_cell
from gwc.client.orders import create_lot, decide, read_traveller
from gwc.errors import GwcError
from gwc.ipc.bus import BlockingBus
from gwc.ipc.codes import LotState, MachineStatus
from gwc.ipc.names import Conv
from gwc.lot.run import spawn_lot_script
from gwc.retry import Deadline
from gwc.soak.cell import PrivateCell
from gwc.soak.plan import FAULTS, Action, LotSpec, Plan, make_plan

PRODUCT = "soak_part"
SCRIPT_ID = "soak"
SCRIPT_PATH = "gwc/lot/scripts/soak.py"
TICK = 0.1
OPERATOR_EVERY = 0.5  # how often the operator looks at the lots and machines
REDECIDE = 5.0  # an import/export the Lot Server refused is asked again after this long
REDISPATCH = 30.0  # an entity left without a script is started again at most this often
RESTART_MACHINE_EVERY = 5.0  # a machine that would not start is tried again after this long
FINAL_STATES = (LotState.EXPORTED.value, LotState.FAILED.value)


@dataclass(frozen=True)
class SoakOptions:
    seed: int
    minutes: float
    var: Path  # the soak's folder: actions.jsonl, report.json, and the private cell under cell/
    database_url: str | None = None  # None: an embedded cluster of the private cell's own
    machines: int = 6
    run_time: float = 0.3  # seconds a dummy machine's run takes
    lot_every: float = 2.0
    action_every: tuple[float, float] = (6.0, 14.0)
    kinds: tuple[str, ...] = ()  # only these fault kinds (empty: all)
    max_active: int = 12
    drain_timeout: float = 360.0  # longer than the lot library's longest step deadline (setup, 300 s)
    script_path: str = SCRIPT_PATH  # the lot script the soak's product runs (a test may break it)
    agent: bool = True  # the host's agent restarts what chaos kills (False: the driver does, as before it)

    def header(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "minutes": self.minutes,
            "machines": self.machines,
            "run_time": self.run_time,
            "lot_every": self.lot_every,
            "action_every": list(self.action_every),
            "kinds": list(self.kinds),
            "max_active": self.max_active,
            "script_path": self.script_path,
            "agent": self.agent,
        }


@dataclass
class SoakReport:
    seed: int
    minutes: float
    lots_planned: int = 0
    lots_created: int = 0
    redispatched: int = 0  # entities the operator had to start a script for again (see Soak._redispatch)
    states: dict[str, int] = field(default_factory=dict)
    failures: dict[str, int] = field(default_factory=dict)  # failure reason -> how many
    faults: dict[str, int] = field(default_factory=dict)  # fault kind -> how many struck
    fault_errors: list[str] = field(default_factory=list)  # faults or repairs the cell did not take
    breaches: list[dict[str, Any]] = field(default_factory=list)
    lot_problems: list[str] = field(default_factory=list)
    leaks: list[str] = field(default_factory=list)
    seconds: float = 0.0
    error: str | None = None

    @property
    def clean(self) -> bool:
        return not (self.error or self.fault_errors or self.breaches or self.lot_problems or self.leaks)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "clean": self.clean}

    def summary(self) -> list[str]:
        lines = [
            f"soak seed {self.seed}, {self.minutes:g} min: {'CLEAN' if self.clean else 'NOT CLEAN'} "
            f"({self.seconds:.0f}s)",
            f"lots: {self.lots_planned} planned, {self.lots_created} created, "
            f"{self.redispatched} restarted by the operator; "
            + ", ".join(f"{k} {v}" for k, v in sorted(self.states.items())),
            "faults: " + (", ".join(f"{k} {v}" for k, v in sorted(self.faults.items())) or "none"),
        ]
        lines += [f"  failed {n}x: {why}" for why, n in sorted(self.failures.items(), key=lambda x: -x[1])[:10]]
        if self.error:
            lines.append(f"ERROR: {self.error}")
        lines += [f"FAULT NOT TAKEN: {e}" for e in self.fault_errors]
        for b in self.breaches:
            lines.append(f"BREACH {b['invariant']}: {b['promise']}")
            lines += [f"  {r}" for r in b["rows"][:10]]
        lines += [f"LOT: {p}" for p in self.lot_problems]
        lines += [f"LEAK: {x}" for x in self.leaks]
        return lines


def plan_header(opts: SoakOptions, plan: Plan) -> dict[str, Any]:
    """The first line of actions.jsonl: every option `--replay` needs, and what the plan holds."""
    return {
        "event": "plan",
        **opts.header(),
        "machine_ids": list(plan.machines),
        "planned_lots": len(plan.lots),
        "planned_faults": len(plan.actions),
        "at": _now(),
    }


def read_header(actions: Path) -> dict[str, Any]:
    """The options a recorded soak ran with (the first line of its actions.jsonl)."""
    try:
        first = json.loads(actions.read_text().split("\n", 1)[0])
    except (OSError, ValueError, IndexError) as e:
        raise GwcError(f"{actions} is not a soak's action log: {e}") from None
    if first.get("event") != "plan":
        raise GwcError(f"{actions} does not start with the soak's plan")
    return first


def action_sequence(actions: Path) -> list[tuple[Any, ...]]:
    """What a recorded soak did, in order, without times: equal for two runs of one seed."""
    out = []
    for line in actions.read_text().splitlines()[1:]:
        e = json.loads(line)
        out.append((e["event"], e["index"], e["kind"], e["target"]))
    return out


class Soak:
    """One soak run (see the module docstring). `run()` returns the report; it never leaves the cell up."""

    def __init__(self, opts: SoakOptions, log: logging.Logger, say: Callable[[str], None] = lambda s: None) -> None:
        self.opts = opts
        self.log = log
        self.say = say
        self.dir = opts.var.resolve()
        machines = [f"wc{i}" for i in range(1, opts.machines + 1)]
        self.plan: Plan = make_plan(opts.seed, opts.minutes, tuple(machines), opts.lot_every, opts.action_every)
        if opts.kinds:
            kept = [a for a in self.plan.actions if a.kind in opts.kinds]
            self.plan = Plan(
                self.plan.seed,
                self.plan.minutes,
                self.plan.machines,
                self.plan.lots,
                [Action(i, a.at, a.kind, a.target, a.downtime, a.seed) for i, a in enumerate(kept)],
            )
        self.report = SoakReport(opts.seed, opts.minutes, lots_planned=len(self.plan.lots))
        self.cell: PrivateCell | None = None
        self.bus: BlockingBus | None = None
        self.conn: psycopg.Connection[Any] | None = None
        self.t0 = 0.0
        self.entities: dict[int, int] = {}  # entity -> plan index
        self.next_lot = 0
        self.next_action = 0
        self.current: tuple[Action, float] | None = None  # the fault in force, and when to repair it
        self.held: set[str] = set()  # machines a fault keeps down: the operator leaves them alone
        self.decided: dict[int, float] = {}
        self.redispatched: dict[int, float] = {}
        self.machine_tried: dict[str, float] = {}
        self.runs: Counter[tuple[str, int]] = Counter()  # RUN_COMPL seen: (machine, machine_run_id)
        self._observer_stop = threading.Event()
        self._last_operator = 0.0

    # ----------------------------------------------------------------- the run

    def run(self) -> SoakReport:
        started = time.monotonic()
        cell_dir = self.dir / "cell"
        if cell_dir.exists():
            shutil.rmtree(cell_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.actions_path = self.dir / "actions.jsonl"
        (self.dir / "lots.jsonl").unlink(missing_ok=True)
        self.actions_path.write_text(json.dumps(plan_header(self.opts, self.plan)) + "\n")
        (self.dir / "plan.json").write_text(json.dumps(self.plan.as_dict(), indent=1))
        machines = [{"id": m, "kind": "dummy", "run_time": self.opts.run_time} for m in self.plan.machines]
        self.cell = PrivateCell(cell_dir, machines, self.log, self.opts.database_url, agent=self.opts.agent)
        observer = None
        try:
            self.say(f"starting a private cell in {cell_dir} ({len(machines)} machines)")
            self.cell.start()
            self.bus = self.cell.bus
            self.conn = db.connect(self.cell.cfg, role="hi", log=self.log)
            self.conn.autocommit = True
            self._register_product()
            observer = threading.Thread(target=self._observe, name="soak-observer", daemon=True)
            observer.start()
            self.say(
                f"running {len(self.plan.lots)} lots and {len(self.plan.actions)} faults for "
                f"{self.opts.minutes:g} min (seed {self.opts.seed})"
            )
            self.t0 = time.monotonic()
            self._chaos_phase()
            self.say("chaos over: repairing everything and waiting for the lots to finish")
            self._repair_all()
            self._drain()
            self._final_checks()
        except GwcError as e:
            self.report.error = str(e)
            self.log.error("soak stopped: %s", e)
        except Exception as e:  # the report must still be written and the cell stopped
            self.report.error = f"{type(e).__name__}: {e}"
            self.log.exception("soak crashed")
        finally:
            self._observer_stop.set()
            if self.conn is not None:
                self.conn.close()
            self.cell.stop()
            if observer is not None:
                observer.join(5)
            self.report.leaks = self.cell.leaks()
            self.report.seconds = time.monotonic() - started
            (self.dir / "report.json").write_text(json.dumps(self.report.as_dict(), indent=1, default=str))
        return self.report

    def _register_product(self) -> None:
        """The soak's lot script and product, registered as the HI registers any (it owns those tables)."""
        assert self.conn is not None
        with self.conn.transaction():
            self.conn.execute(
                "INSERT INTO lot_scripts (script_id, path, description) VALUES (%s, %s, %s) "
                "ON CONFLICT (script_id) DO UPDATE SET path = EXCLUDED.path",
                (SCRIPT_ID, self.opts.script_path, "the chaos soak's lot"),
            )
            self.conn.execute(
                "INSERT INTO products (product_id, description, script_id) VALUES (%s, %s, %s) "
                "ON CONFLICT (product_id) DO UPDATE SET script_id = EXCLUDED.script_id",
                (PRODUCT, "a part the soak makes", SCRIPT_ID),
            )

    def _observe(self) -> None:
        """Thread: count every RUN_COMPL on the bus, to find a run reported twice."""
        assert self.cell is not None
        with BlockingBus(f"soak.obs.{id(self):x}", self.cell.cfg.bus, self.log, interest=(Conv.RUN_COMPL,)) as bus:
            while not self._observer_stop.is_set():
                conv = bus.first_message(timeout=0.5)
                if conv is None or conv.first is None:
                    continue
                m = conv.first.first
                conv.end()
                if m.machine_run_id is not None:
                    self.runs[(m.machine_id, int(m.machine_run_id))] += 1

    def _elapsed(self) -> float:
        return time.monotonic() - self.t0

    def _chaos_phase(self) -> None:
        duration = self.opts.minutes * 60.0
        while self._elapsed() < duration or self.current is not None:
            self._order_lots(until=min(self._elapsed(), duration))
            self._operate()
            self._chaos()
            time.sleep(TICK)

    # ----------------------------------------------------------------- the order desk

    def _active(self) -> int:
        assert self.conn is not None
        row = self.conn.execute("SELECT count(*) FROM lot_status WHERE state NOT IN (%s, %s)", FINAL_STATES).fetchone()
        return int(row[0]) if row else 0

    def _order_lots(self, until: float) -> None:
        while self.next_lot < len(self.plan.lots) and self.plan.lots[self.next_lot].at <= until:
            if self._active() >= self.opts.max_active or not self._up("ls"):
                return
            spec = self.plan.lots[self.next_lot]
            try:
                self._order(spec)
            except GwcError as e:
                self.log.warning("lot %d could not be ordered yet: %s", spec.index, e)
                return
            self.next_lot += 1

    def _order(self, spec: LotSpec) -> None:
        assert self.bus is not None and self.cell is not None
        lot_id, entities = create_lot(
            self.bus,
            PRODUCT,
            1,
            priority=spec.priority,
            owner="soak",
            timeout=5.0,
            within=0,
            request_id=f"{self.bus.bus.name}.{self.bus.bus.inc:x}.{spec.index}",
        )
        self._dispatch(lot_id, entities, spec)

    def _dispatch(self, lot_id: int, entities: list[int], spec: LotSpec) -> None:
        assert self.cell is not None
        plan_dir = self.cell.cfg.var / "soak"
        plan_dir.mkdir(parents=True, exist_ok=True)
        body = {
            "index": spec.index,
            "alternatives": spec.alternatives,
            "priority": spec.priority,
            "op_type": spec.op_type,
        }
        (plan_dir / f"lot-{lot_id}.json").write_text(json.dumps(body))
        for e in entities:
            self.entities[e] = spec.index
            pid = spawn_lot_script(self.cell.cfg, e)
            self._record("lot", spec.index, "order", str(e), detail=f"lot {lot_id}, pid {pid}")
        self.report.lots_created += 1

    # ----------------------------------------------------------------- the operator

    def _up(self, *names: str) -> bool:
        """Whether these servers are on the bus and started: asking one that is not only blocks the desk."""
        assert self.bus is not None
        peers = self.bus.peers()
        return all(n in peers and Conv.SHUTDOWN in peers[n].interest for n in names)

    def _operate(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_operator < OPERATOR_EVERY:
            return
        self._last_operator = now
        assert self.conn is not None and self.bus is not None and self.cell is not None
        if self._up("ls"):
            self._decide(now)
            self._redispatch(now)
        if self._up("ms", "msched"):
            self._start_machines(now)

    def _decide(self, now: float) -> None:
        """Import what waits to be imported, export what waits to be exported."""
        assert self.conn is not None and self.bus is not None
        waiting = self.conn.execute(
            "SELECT entity_id, state FROM lot_status WHERE state IN (%s, %s) ORDER BY 1",
            (LotState.WAITING_IMPORT.value, LotState.WAITING_EXPORT.value),
        ).fetchall()
        for entity, state in waiting:
            if now - self.decided.get(entity, -REDECIDE) < REDECIDE:
                continue
            self.decided[entity] = now
            action = "import" if state == LotState.WAITING_IMPORT else "export"
            try:
                decide(self.bus, int(entity), action, "soak")
            except GwcError as e:
                self.log.info("operator: %s of entity %s not taken yet: %s", action, entity, e)

    def _redispatch(self, now: float) -> None:
        """An entity still `created` with no living script is started again, as the operator would from
        `gwc lots`: its script died before the Lot Server heard of it (the server was down), or the
        answer to its order was lost so nobody started one."""
        assert self.conn is not None and self.cell is not None
        rows = self.conn.execute(
            "SELECT entity_id, lot_id FROM lot_status WHERE state = 'created' "
            "AND updated_at < now() - interval '15 seconds' ORDER BY 1"
        ).fetchall()
        for entity, lot_id in rows:
            e = int(entity)
            if self.cell.alive(f"lot:{e}") or now - self.redispatched.get(e, -REDISPATCH) < REDISPATCH:
                continue
            self.redispatched[e] = now
            known = e in self.entities
            self.log.warning(
                "operator: entity %d of lot %s is created with no script running (%s): starting it",
                e,
                lot_id,
                "its script died unheard" if known else "its order's answer was lost",
            )
            self.report.redispatched += 1
            pid = spawn_lot_script(self.cell.cfg, e)
            self._record("lot", self.entities.get(e, -1), "redispatch", str(e), detail=f"lot {lot_id}, pid {pid}")

    def _start_machines(self, now: float) -> None:
        """A machine down that no fault holds down is started again through the HI."""
        assert self.conn is not None and self.cell is not None
        status = dict(self.conn.execute("SELECT machine_id, status FROM machine_status").fetchall())
        for m in self.plan.machines:
            if status.get(m) != MachineStatus.SHUTDOWN or m in self.held:
                continue
            if not all(self.cell.alive(p.name) for p in machine_procs(self.cell.cfg, m)):
                continue
            if now - self.machine_tried.get(m, -RESTART_MACHINE_EVERY) < RESTART_MACHINE_EVERY:
                continue
            self.machine_tried[m] = now
            try:
                out = self.cell.machine_start(m)
                self.log.info("operator: machine %s was down: %s", m, out)
            except GwcError as e:
                self.log.warning("operator: machine %s would not start: %s", m, e)

    # ----------------------------------------------------------------- chaos

    def _chaos(self) -> None:
        if self.current is not None:
            action, repair_at = self.current
            if self._elapsed() >= repair_at:
                self._repair(action)
            return
        if self.next_action < len(self.plan.actions) and self.plan.actions[self.next_action].at <= self._elapsed():
            action = self.plan.actions[self.next_action]
            self.next_action += 1
            self._strike(action)

    def _procs_of(self, action: Action) -> list[str]:
        assert self.cell is not None
        if action.kind == "kill_wc":
            return [f"wc:{action.target}"]
        if action.kind == "kill_me":
            return [f"me:{action.target}"]
        if action.kind == "kill_pair":
            return [p.name for p in machine_procs(self.cell.cfg, action.target)]
        if action.kind in ("kill_server", "faults"):
            return [action.target]
        return []

    def _strike(self, action: Action) -> None:
        assert self.cell is not None
        detail = ""
        try:
            if action.kind == "machine_stop":
                self.held.add(action.target)
                detail = self.cell.hi("machine", "stop", action.target)
            elif action.kind == "kill_lot":
                detail = self._kill_lot(action)
            else:
                if action.kind in ("kill_wc", "kill_me", "kill_pair"):
                    self.held.add(action.target)
                killed = [f"{n} pid {self.cell.kill(n)}" for n in self._procs_of(action)]
                detail = "killed " + ", ".join(killed)
                if action.kind == "faults":
                    cfg = self.cell.faults_config(action.seed, FAULTS)
                    detail += f"; restarted pid {self.cell.restart(action.target, cfg)} with bus faults {FAULTS}"
        except GwcError as e:
            self.report.fault_errors.append(f"{action.describe()}: {e}")
            detail = f"error: {e}"
        self.report.faults[action.kind] = self.report.faults.get(action.kind, 0) + 1
        self._record("fault", action.index, action.kind, action.target, detail, planned=action.at)
        self.current = (action, self._elapsed() + action.downtime)

    def _kill_lot(self, action: Action) -> str:
        assert self.cell is not None
        scripts = sorted(p.stem for p in self.cell.cfg.run_dir.glob("lot-*.pid"))
        alive = [s.replace("-", ":", 1) for s in scripts if self.cell.alive(s.replace("-", ":", 1))]
        if not alive:
            return "no lot script running"
        name = random.Random(action.seed).choice(alive)
        return f"killed {name} pid {self.cell.kill(name)}"

    def _repair(self, action: Action, attempts: int = 3) -> None:
        assert self.cell is not None
        detail = ""
        for attempt in range(1, attempts + 1):
            try:
                if action.kind == "machine_stop":
                    detail = self.cell.machine_start(action.target)
                elif action.kind == "kill_lot":
                    detail = (
                        "nothing to restart: the agent restarted it, its entity resumes"
                        if self.cell.agent
                        else "nothing to restart: the Lot Server reaps the entity"
                    )
                elif action.kind == "faults":
                    self.cell.kill(action.target)
                    detail = f"healed: restarted pid {self.cell.restart(action.target)} without faults"
                elif self.cell.agent:  # it restarted them already: make sure they are up
                    detail = "up again (agent): " + ", ".join(
                        f"{n} pid {self.cell.restart(n)}" for n in self._procs_of(action)
                    )
                else:
                    pids = [f"{n} pid {self.cell.restart(n)}" for n in self._procs_of(action) if not self.cell.alive(n)]
                    detail = "restarted " + (", ".join(pids) or "nothing")
                break
            except GwcError as e:
                detail = f"error (try {attempt}): {e}"
                self.log.error("repair of %s failed: %s", action.describe(), e)
                if attempt == attempts:
                    self.report.fault_errors.append(f"repair of {action.describe()}: {e}")
        self.held.discard(action.target)
        self._record("repair", action.index, action.kind, action.target, detail)
        self.current = None

    def _repair_all(self) -> None:
        """After the chaos: every process running, every server started, every machine up."""
        assert self.cell is not None and self.bus is not None
        if self.current is not None:
            self._repair(self.current[0])
        try:
            start_procs(self.cell.cfg, cell_procs(self.cell.cfg), self.bus, self.log.info)
        except GwcError as e:
            self.report.fault_errors.append(f"restarting the cell after the chaos: {e}")
        self.held.clear()
        self.machine_tried.clear()
        self._operate(force=True)

    def _drain(self) -> None:
        """Order what the desk held back (max_active), then wait for every lot to finish."""
        assert self.conn is not None
        deadline = Deadline(self.opts.drain_timeout)
        while not deadline.expired:
            self._order_lots(until=float("inf"))
            self._operate()
            if self.next_lot == len(self.plan.lots) and self._active() == 0:
                return
            time.sleep(TICK * 2)
        self.log.error("drain: lots still unfinished after %.0fs", self.opts.drain_timeout)

    # ----------------------------------------------------------------- the verdict

    def _final_checks(self) -> None:
        assert self.conn is not None and self.cell is not None and self.bus is not None
        self.say("checking the invariants and accounting for every lot")
        breaches = check_cell(self.cell.cfg, self.conn, self.bus, settle=3.0)
        self.report.breaches = [b.as_dict() for b in breaches]
        rows = self.conn.execute("SELECT entity_id, lot_id, state, reason FROM lot_status ORDER BY 1").fetchall()
        states = Counter(str(r[2]) for r in rows)
        self.report.states = dict(states)
        problems = self.report.lot_problems
        for entity, _lot_id, state, reason in rows:
            if state not in FINAL_STATES:
                problems.append(f"{self._lot_name(entity)} is {state}: neither exported nor failed")
            elif state == LotState.FAILED and not (reason or "").strip():
                problems.append(f"{self._lot_name(entity)} failed without a reason")
            if state == LotState.FAILED:
                key = _reason_kind(reason or "")
                self.report.failures[key] = self.report.failures.get(key, 0) + 1
        known = {int(r[0]) for r in rows}
        ordered = set(self.entities)
        for e in sorted(ordered - known):
            problems.append(f"entity {e} (lot #{self.entities[e]}) was ordered and is lost: no LOT_STATUS row")
        never = len(self.plan.lots) - len(set(self.entities.values()))
        if never:
            problems.append(f"{never} planned lot(s) were never ordered")
        # Run twice: an entity with two operations done, or a machine_run_id claimed by two entities.
        owner: dict[int, int] = {}
        for e in sorted(known):
            trav = read_traveller(self.cell.cfg, e) or {}
            done = [s for s in trav.get("steps", []) if s.get("runs")]
            if len(done) > 1:
                problems.append(
                    f"{self._lot_name(e)} ran {len(done)} times: runs "
                    + ", ".join(str(s["machine_run_id"]) for s in done)
                )
            for s in trav.get("steps", []):
                run_id = int(s["machine_run_id"])
                if run_id in owner and owner[run_id] != e:
                    problems.append(f"machine_run_id {run_id} was given to entities {owner[run_id]} and {e}")
                owner[run_id] = e
        for (machine, run_id), n in sorted(self.runs.items()):
            if n > 1:
                problems.append(f"run {run_id} on {machine} was reported complete {n} times")

    def _lot_name(self, entity: int) -> str:
        """'lot #7 (entity 12)': the plan's index is what two runs of one seed share."""
        index = self.entities.get(entity)
        if index is None:
            return f"entity {entity} (of an order whose answer was lost)"
        return f"lot #{index} (entity {entity})"

    def _record(
        self, event: str, index: int, kind: str, target: str, detail: str = "", planned: float | None = None
    ) -> None:
        entry = {
            "event": event,
            "index": index,
            "kind": kind,
            "target": target,
            "t": round(self._elapsed(), 3),
            "at": _now(),
            "detail": detail,
        }
        if planned is not None:
            entry["planned"] = planned
        if event != "lot":
            with self.actions_path.open("a") as f:
                f.write(json.dumps(entry) + "\n")
            self.say(f"[{entry['t']:7.1f}s] {event} {kind} {target}: {detail}")
        else:
            with (self.dir / "lots.jsonl").open("a") as f:
                f.write(json.dumps(entry) + "\n")
        self.log.info("%s %s %s: %s", event, kind, target, detail)


def _reason_kind(reason: str) -> str:
    """A failure reason without its numbers, so alike failures count together."""
    out = []
    for word in reason.split():
        out.append("N" if any(c.isdigit() for c in word) else word)
    return " ".join(out)[:160]


def _now() -> str:
    return datetime.now().isoformat(" ", "milliseconds")


def run_soak(opts: SoakOptions, log: logging.Logger, say: Callable[[str], None] = lambda s: None) -> SoakReport:
    return Soak(opts, log, say).run()


__all__ = ["Soak", "SoakOptions", "SoakReport", "action_sequence", "plan_header", "read_header", "run_soak"]
