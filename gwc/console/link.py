"""The console's side of the cell, without a user interface: what it hears, reads and asks.

* It hears the bus as the monitor does (a silent listener thread, gwc.hi.monitor.watch): every
  conversation is kept for the monitor view and names the views it makes stale (VIEWS_OF), so a
  view is read again only when the cell said something that concerns it.
* It reads what the bus does not carry (the rows behind a view) on one database connection kept
  open as role gwc_hi, opened again after the database comes back.
* It acts through its own bus attachment (a `hi.` name like every `gwc` command), with the very
  functions the `gwc` commands call, so an action is the same conversation the command holds; each
  answer comes back as an Answer with the ack code in words.
"""

from __future__ import annotations

import collections
import getpass
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import psycopg
from psycopg.pq import TransactionStatus

from gwc import cell, db
from gwc.agent import control as agent_control
from gwc.client.alarms import clear_alarm, read_status_line
from gwc.client.machines import maintenance_done, start_machine, stop_machine
from gwc.client.orders import decide, enter_order
from gwc.client.requests import cancel_request, unreserve_machine
from gwc.config import Config
from gwc.errors import Forbidden, GwcError, Refused
from gwc.hi.monitor import watch
from gwc.ipc import BlockingBus, Peer
from gwc.ipc.codes import AckCode, LotState
from gwc.ipc.names import Conv
from gwc.log import log_file_name, open_log
from gwc.module import module_name
from gwc.users import Action, Person, check, identify_unix
from gwc.users.doors import audit

T = TypeVar("T")

RECORDS_MAX = 5000  # conversations held for the monitor view between two looks
DB_RETRY = 2.0  # seconds between attempts to reach a database that is down
START_TIMEOUT = 600.0  # a machine being homed waits for its operator (as `gwc machine start`)
STOP_TIMEOUT = 60.0

# Which views each conversation class makes stale. The status line follows what it counts.
VIEWS_OF: dict[str, tuple[str, ...]] = {
    Conv.MOD_DIED: ("modules",),
    Conv.STARTUP: ("modules",),
    Conv.SHUTDOWN: ("modules",),
    Conv.ME_START: ("machines", "modules"),
    Conv.ME_SHUT: ("machines", "modules", "requests"),
    Conv.UPD_ME_ST: ("machines", "requests", "record"),
    Conv.DOWNTIME_RSN: ("record",),
    Conv.CHG_STATUS: ("machines",),
    Conv.ACC_TYP_C: ("machines",),
    Conv.MAINT_DONE: ("machines",),
    Conv.SETUP_RUN: ("machines",),
    Conv.START_RUN: ("machines",),
    Conv.RUN_COMPL: ("machines", "lots", "record", "spc"),
    Conv.MACH_REQ: ("requests", "lots"),
    Conv.CANCEL_RE: ("requests", "lots"),
    Conv.UNRESERVE: ("requests", "lots"),
    Conv.CREATE_LOT: ("lots", "orders"),
    Conv.ENTITY_REQ: ("lots", "orders", "status"),
    Conv.IMPORT_LOT: ("lots", "orders", "status"),
    Conv.EXPORT_LOT: ("lots", "orders", "status"),
    Conv.LOT_MOVED: ("lots", "orders", "status"),
    Conv.DIV_MERGE: ("lots", "orders"),
    Conv.ALARM_SEND: ("alarms", "status"),
    Conv.ALARM_CLE: ("alarms", "status"),
    Conv.ALARM_CLR_REQ: ("alarms", "status"),
    Conv.CELL_EVENT: ("status",),
}


@dataclass(frozen=True)
class Answer:
    """The cell's answer to one action, as the console shows it."""

    ok: bool
    text: str


def in_words(code: str) -> str:
    """An ack code and what it means: `Notnow (the module or machine is in a state ...)`."""
    try:
        return f"{code} ({AckCode(code).words})"
    except ValueError:
        return str(code)


REFUSED = "refused by the role table: "  # the start of a refusal's answer (already audited)
DECISIONS = {"import": Action.LOT_IMPORT, "export": Action.LOT_EXPORT}


def console_log(cfg: Config) -> logging.Logger:
    """The console's log, var/log/console.log (at the HI's level)."""
    return open_log("console", cfg.log_dir, cfg.level_of("hi"))


def operator() -> str:
    """Who the console acts for, as the cell's history records it."""
    try:
        return f"console:{getpass.getuser()}"
    except (KeyError, OSError):
        return f"console:{os.getuid()}"


class CellLink:
    """One console's attachment to a cell. open() before use, close() at the end (safe twice)."""

    def __init__(self, cfg: Config, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        self.bus: BlockingBus | None = None
        self.name = f"hi.console.{os.getpid()}"
        self.db_error: str | None = None
        self.reads = 0  # database reads made for the views: the console's cost to the cell, shown on screen
        self._conn: psycopg.Connection[Any] | None = None
        self._conn_lock = threading.Lock()
        self._next_connect = 0.0
        self._records: collections.deque[dict[str, Any]] = collections.deque(maxlen=RECORDS_MAX)
        self._stop = threading.Event()
        self._listener: threading.Thread | None = None
        self.person: Person | None = None  # who sits at the console (gwc.users), known at the first action

    # ----------------------------------------------------------------- lifetime

    def open(self) -> None:
        # A name of its own: `gwc demo --console` holds the demo's HI bus (hi.<pid>) in this process too.
        self.bus = BlockingBus(self.name, self.cfg.bus, self.log)
        self._listener = threading.Thread(target=self._listen, name="console-listener", daemon=True)
        self._listener.start()

    def close(self) -> None:
        self._stop.set()
        if self._listener is not None:
            self._listener.join(2)
        if self.bus is not None:
            self.bus.close()
        with self._conn_lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def _listen(self) -> None:
        try:
            watch(self.cfg.bus, self._records.append, self._stop.is_set)
        except Exception:  # the views go on without it; the log says why
            self.log.exception("console: the bus listener stopped")

    def heard(self) -> list[dict[str, Any]]:
        """Every conversation message heard since the last call, oldest first."""
        out = []
        while self._records:
            out.append(self._records.popleft())
        return out

    # ----------------------------------------------------------------- the bus

    def peers(self) -> dict[str, Peer]:
        """The modules on the bus now (other HIs and consoles left out)."""
        assert self.bus is not None
        return {n: p for n, p in self.bus.peers().items() if not n.startswith("hi.")}

    def modules_up(self) -> set[str]:
        """The cell's own modules (cell.toml's) on the bus now: none means the cell is down."""
        mine = {m.name for m in self.cfg.modules} | {module_name("wc", m.id) for m in self.cfg.machines}
        return set(self.peers()) & mine

    def _need(self, name: str) -> None:
        if name not in self.peers():
            raise GwcError(f"{name} is not on the bus: is the cell running?")

    # ----------------------------------------------------------------- the database

    def read(self, fn: Callable[[psycopg.Connection[Any]], T]) -> T | None:
        """fn(conn) on the console's connection, in one transaction; None while the database cannot be
        reached (db_error says why)."""
        with self._conn_lock:
            if self._conn is None or self._conn.closed:
                if time.monotonic() < self._next_connect:
                    return None
                try:
                    self._conn = db.connect(self.cfg, role="hi", log=self.log, attempts=1)
                except GwcError as e:
                    self._next_connect = time.monotonic() + DB_RETRY
                    self.db_error = f"unreachable ({str(e).split(' (')[0]})"
                    return None
            try:
                try:
                    result = fn(self._conn)
                finally:  # one read, one transaction (not one per statement): ended, whatever fn did
                    if not self._conn.closed and self._conn.info.transaction_status != TransactionStatus.IDLE:
                        self._conn.rollback()
            except (psycopg.OperationalError, psycopg.InterfaceError) as e:  # the server went, or the connection
                self.log.warning("console: database read failed: %s", e)
                self.db_error = "unreachable (the connection was lost; trying again)"
                self._conn.close()
                self._conn = None
                return None
            self.db_error = None
            self.reads += 1
            return result

    # ----------------------------------------------------------------- actions (worker threads)

    def act(self, what: str, fn: Callable[[], str], action: Action | None = None, target: str = "") -> Answer:
        """Run one action; its answer (or why it was refused) as one line, logged to the console's log.
        `action`: what it is in the role table (docs/users.md): checked for the person at the console
        before it runs, and its outcome appended to the audit trail (gwc.users)."""
        try:
            if action is not None:
                self._check(action, target)
            answer = Answer(True, f"{what}: {fn()}")
        except Refused as e:
            answer = Answer(False, f"{what}: refused, {in_words(e.ack_code)}" + _detail(e))
        except GwcError as e:
            answer = Answer(False, f"{what}: {e}")
        except Exception as e:  # not the cell's answer but a fault here: said, logged whole, the console goes on
            self.log.exception("console: %s failed", what)
            answer = Answer(False, f"{what}: failed, {type(e).__name__}: {e} (see {self.log_path()})")
        self.log.info("%s", answer.text)
        if action is not None and self.person is not None and not answer.text.startswith(f"{what}: {REFUSED}"):
            who, outcome = self.person, "ok" if answer.ok else "failed"

            def write(conn: psycopg.Connection[Any]) -> bool:
                audit(conn, who, action, target, outcome, answer.text)
                return True

            if self.read(write) is None:
                self.log.error("console: audit row not written: %s", answer.text)
        return answer

    def _check(self, action: Action, target: str) -> None:
        """The person at the console (their unix login, as for a `gwc` command, found at the first
        action) may do `action`, or Forbidden (audited) naming the roles that may. Once known, the
        person's role is checked here without the database, so that an operator can still stop a
        machine while the database is away (the audit row is then lost, and logged)."""
        if self.person is None:
            found = self.read(lambda conn: identify_unix(conn, "console"))
            if found is None:
                raise GwcError(f"cannot tell who you are: the cell database is {self.db_error or 'unreachable'}")
            self.person = found
        who = self.person
        try:
            check(who.name, who.role, action)
        except Forbidden as e:
            why = str(e)

            def write(conn: psycopg.Connection[Any]) -> bool:
                audit(conn, who, action, target, "refused", why)
                return True

            if self.read(write) is None:
                self.log.error("console: audit row not written: %s %s refused to %s", action, target, who.name)
            self.log.warning("console: %s %s refused to %s: %s", action, target, who.name, e)
            raise GwcError(f"{REFUSED}{e}") from None

    def log_path(self) -> Path:
        return self.cfg.log_dir / log_file_name("console")

    def decide(self, entity_id: int, action: str) -> Answer:
        """IMPORT_LOT or EXPORT_LOT, as `gwc import` / `gwc export`."""

        def go() -> str:
            assert self.bus is not None
            self._need("ls")
            lot = decide(self.bus, entity_id, action, operator())
            return f"{in_words(AckCode.ACK_OK)}, lot {lot}"

        return self.act(f"{action} entity {entity_id}", go, DECISIONS[action], str(entity_id))

    def decide_all(self, action: str, entities: Iterable[int]) -> list[Answer]:
        return [self.decide(e, action) for e in entities]

    def start_machine(self, machine_id: str) -> Answer:
        """Its processes if they are down, then ME_START, as `gwc machine start`."""

        def go() -> str:
            assert self.bus is not None
            return start_machine(self.cfg, self.bus, machine_id, self.log.info, START_TIMEOUT)

        return self.act(f"start machine {machine_id} (ME_START)", go, Action.MACHINE_START, machine_id)

    def stop_machine(self, machine_id: str) -> Answer:
        """ME_SHUT, as `gwc machine stop`."""

        def go() -> str:
            assert self.bus is not None
            return stop_machine(self.cfg, self.bus, machine_id, STOP_TIMEOUT)

        return self.act(f"stop machine {machine_id} (ME_SHUT)", go, Action.MACHINE_STOP, machine_id)

    def maintenance_done(self, machine_id: str) -> Answer:
        """MAINT_DONE, as `gwc machine maintenance-done`."""

        def go() -> str:
            assert self.bus is not None
            self._need("ms")
            runs = maintenance_done(self.bus, machine_id)
            return f"{in_words(AckCode.ACK_OK)}: maintained after {runs} run(s), the count starts again"

        return self.act(f"maintenance done on {machine_id}", go, Action.MACHINE_MAINTAINED, machine_id)

    def start_module(self, name: str) -> Answer:
        """A WC: ME_START. A server: through the agent where one runs (as `gwc start`), else its
        process if it is not running, then STARTUP."""
        if name.startswith("wc:"):
            return self.start_machine(name[3:])

        def go() -> str:
            assert self.bus is not None
            if name in self.peers() and not agent_control.running(self.cfg):
                return cell.startup(self.bus, name)
            procs = [p for p in cell.cell_procs(self.cfg) if p.name == name]
            if not procs:
                raise GwcError(f"{name} is not a module of this cell ({self.cfg.path})")
            said: list[str] = []
            cell.start_procs(self.cfg, procs, self.bus, said.append)
            return "; ".join(said) or "started"

        return self.act(f"start {name}", go, Action.MACHINE_START, name)

    def stop_module(self, name: str) -> Answer:
        """A WC: ME_SHUT. A server: the agent stops its process (and keeps it down) where one runs;
        else SHUTDOWN (it stays on the bus, listening for STARTUP)."""
        if name.startswith("wc:"):
            return self.stop_machine(name[3:])

        def go() -> str:
            assert self.bus is not None
            if agent_control.running(self.cfg):
                said: list[str] = []
                agent_control.call(self.cfg, "stop", say=said.append, names=[name])
                return "; ".join(said) or "stopped by the agent"
            self._need(name)
            return cell.shutdown(self.bus, name)

        return self.act(f"stop {name}", go, Action.MACHINE_STOP, name)

    def restart_module(self, name: str) -> Answer:
        """Stop and start a module's process through the agent, as `gwc restart`."""

        def go() -> str:
            said: list[str] = []
            agent_control.call(self.cfg, "restart", say=said.append, names=[name])
            return "; ".join(said) or "restarted"

        return self.act(f"restart {name}", go, Action.MACHINE_START, name)

    def start_cell(self) -> Answer:
        """Database, servers and machines' processes, as `gwc start`."""

        def go() -> str:
            cell.start_cell(self.cfg, self.log, say=self.log.info)
            return "cell started"

        return self.act("start the cell", go, Action.MACHINE_START, "cell")

    def clear_alarm(self, alarm_no: int) -> Answer:
        """ALARM_CLR_REQ, as `gwc alarm clear`."""

        def go() -> str:
            assert self.bus is not None
            self._need("cas")
            ack = clear_alarm(self.bus, alarm_no, operator())
            if ack.ack_code != AckCode.ACK_OK:
                raise Refused(ack.ack_code, ack.note or "")
            return in_words(ack.ack_code)

        return self.act(f"clear alarm {alarm_no}", go, Action.ALARM_CLEAR, str(alarm_no))

    def cancel_request(self, request_key: int) -> Answer:
        """CANCEL_RE, as `gwc cancel`."""

        def go() -> str:
            assert self.bus is not None
            self._need("msched")
            ack = cancel_request(self.bus, request_key, None, operator())
            if ack.ack_code != AckCode.ACK_OK:
                raise Refused(ack.ack_code, ack.note or "")
            return f"{in_words(ack.ack_code)}: {ack.cancelled} request(s) cancelled, the entity was told REQ_CANCEL"

        return self.act(f"cancel request {request_key}", go, Action.REQUEST_CANCEL, str(request_key))

    def unreserve_machine(self, machine_id: str) -> Answer:
        """UNRESERVE of a machine a dead lot holds, as `gwc unreserve` (refused while its script runs)."""

        def go() -> str:
            assert self.bus is not None
            self._need("msched")
            entity = unreserve_machine(self.cfg, self.bus, machine_id)
            return f"{in_words(AckCode.ACK_OK)}: {machine_id} freed (it was reserved to entity {entity})"

        return self.act(f"unreserve {machine_id}", go, Action.MACHINE_UNRESERVE, machine_id)

    def enter_order(self, customer: str, items: list[tuple[str, int]]) -> Answer:
        """Work Order Entry, as `gwc order new`: the order, its lots, one lot script per entity."""

        def go() -> str:
            assert self.bus is not None
            made = enter_order(self.cfg, self.log, self.bus, customer, items)
            lots = "; ".join(
                f"lot {lot['lot_id']}: {lot['quantity']} x {lot['product_id']} "
                f"(entities {', '.join(map(str, lot['entities']))})"
                for lot in made["lots"]
            )
            return f"work order {made['work_order_id']} entered, {lots}"

        return self.act(f"work order for {customer}", go, Action.ORDER_ENTER, customer)

    def status_line(self) -> str:
        """The Status Line Server's line (STATUS_LN), as `gwc status-line`."""
        assert self.bus is not None
        if "sls" not in self.peers():
            return "Status Line Server not on the bus"
        try:
            return read_status_line(self.bus).text
        except GwcError as e:
            return f"status line: {e}"
        except Exception as e:  # a fault here, not the cell's: the line says so and the console goes on
            self.log.exception("console: reading the status line failed")
            return f"status line: could not be read, {type(e).__name__}: {e} (see {self.log_path()})"


def _detail(e: Refused) -> str:
    text = str(e)
    _, _, detail = text.partition(": ")
    return f": {detail}" if detail else ""


WAITING = {"import": LotState.WAITING_IMPORT.value, "export": LotState.WAITING_EXPORT.value}
