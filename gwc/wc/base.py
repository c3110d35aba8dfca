"""What the WC's parts share: the machine's state as the WC knows it (MachineState), what a part may ask
of the WC module that holds it (WcHost), and the WC's calls to the cell's servers (ServerCalls): status
changes (Machine Server), accept types (MSCHED), alarms (Cell Alarm Server), recipes (Equipment Recipe
Server) and its reads (see gwc/wc/wc.py)."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import psycopg

from gwc.config import Config
from gwc.db import Statement
from gwc.errors import ConversationTimeout, DatabaseError, GwcError
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S

# Ping the ME after this long without hearing from it: each ping wakes both halves (docs/performance.md,
# A resting cell). An ME whose process exits is pinged at the next heartbeat (the WC watches its process),
# so this bounds only finding one that hangs: ME_PING + a heartbeat + ME_DEADLINE.
ME_PING = 5.0
ME_DEADLINE = 1.5  # an ME silent this long after a ping is dead
SERVER_TIMEOUT = 5.0  # longest a server may take to answer the WC
# How long the WC asks a restarting server (or one whose database is away) again: status, accept types.
SERVER_RESTART = DATABASE_OUTAGE_S
ABANDONED_S = 10.0  # a setup whose run has not been reserved this long is given up (its lot is gone)
SETUP_CHECK_S = 2.0  # how often a machine in Setup looks for its run's reservation
ALL_OPERATIONS = ["*"]

T = TypeVar("T")


class WcHost(Protocol):
    """What the WC's parts use of the module that holds them (gwc.module.Module's public side)."""

    cfg: Config
    name: str
    log: logging.Logger
    bus: Bus
    started: bool

    async def ask(
        self,
        cls: str,
        first: Message,
        to: str | None,
        timeout: float | None = None,
        *more: Message,
        within: float = 0.0,
    ) -> Message: ...

    def transaction(self, fn: Callable[[psycopg.Cursor[Any]], T]) -> T: ...

    async def transaction_when_up(self, fn: Callable[[psycopg.Cursor[Any]], T], within: float | None = None) -> T: ...

    def idle_interest(self) -> set[str]: ...

    def busy_interest(self) -> set[str]: ...

    def spawn(self, coro: Coroutine[Any, Any, object]) -> None: ...


@dataclass
class MachineState:
    """The machine as its WC knows it; the Machine Server holds the truth (MACHINE_STATUS)."""

    machine_id: str
    recipe_dir: Path
    results_dir: Path
    status: MachineStatus = MachineStatus.SHUTDOWN  # our copy of MACHINE_STATUS.status
    machine_run_id: int | None = None
    recipe_id: str | None = None
    # One status-changing step at a time: setup, start, a run's end, shutdown, lost and back.
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    set_up_for: tuple[str, int] | None = None  # (asker, machine_run_id) of the last setup, its reservation checked

    def clear_run(self) -> None:
        """No run and no recipe on the machine any more."""
        self.machine_run_id = self.recipe_id = None

    def results_path(self, run_id: int) -> Path:
        """Where the ME writes run `run_id`'s results: chosen by the WC, so a restarted WC finds them."""
        return self.results_dir / f"run-{run_id}.txt"

    def recipe_file(self, recipe_id: str, version: int) -> Path:
        return self.recipe_dir / f"{recipe_id}.v{version}"


class ServerCalls:
    """The WC's conversations with the servers, and its reads of the tables."""

    def __init__(self, host: WcHost, state: MachineState) -> None:
        self.host = host
        self.state = state
        self._accept_lock = asyncio.Lock()  # accept-type changes reach MSCHED one at a time, in order
        # A setup's accepts-nothing, asked in the background and not answered yet: the run's end waits for it.
        self.accepting_none: asyncio.Future[bool] | None = None
        self._alarm_waits: dict[int, asyncio.Future[None]] = {}
        self._cleared: set[int] = set()  # alarm numbers seen cleared (a clear may beat our wait for it)

    # ----------------------------------------------------------------- reads

    def read(self, sql: str, params: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """One row read; DatabaseError if the database refuses it, DatabaseUnavailable if it is away."""
        return self.host.transaction(Statement(sql, params))

    async def read_when_up(self, sql: str, params: tuple[Any, ...] | dict[str, Any]) -> tuple[Any, ...] | None:
        """One row read for a step a lot waits on: a database outage is waited out (DATABASE_OUTAGE_S)."""
        return await self.host.transaction_when_up(Statement(sql, params), DATABASE_OUTAGE_S)

    def read_status(self) -> tuple[MachineStatus, int | None, str | None]:
        """The machine's MACHINE_STATUS row: status, machine_run_id, recipe_id."""
        row = self.read(
            "SELECT status, machine_run_id, recipe_id FROM machine_status WHERE machine_id = %s",
            (self.state.machine_id,),
        )
        return (MachineStatus(row[0]), row[1], row[2]) if row else (MachineStatus.SHUTDOWN, None, None)

    # ----------------------------------------------------------------- the Machine Server, MSCHED

    async def change_status(
        self, status: MachineStatus, expect: list[MachineStatus] | None = None, **fields: Any
    ) -> bool:
        """Ask the Machine Server to change our status; keep our copy in step when it agrees."""
        log, state = self.host.log, self.state
        try:
            answer = await self.host.ask(
                Conv.CHG_STATUS,
                message(
                    Msg.CHANGE_STATUS,
                    machine_id=state.machine_id,
                    status=status,
                    expect=[str(s) for s in expect] if expect else None,
                    **fields,
                ),
                "ms",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            log.error("Machine Server did not answer the change to %s", status)
            return False
        # A refusal that names the status asked for is no refusal: asked again after the Machine
        # Server restarted, the first change had been made.
        if answer.ack_code != AckCode.ACK_OK and answer.status != status:
            log.error("Machine Server refused %s: %s %s", status, answer.ack_code, answer.note or "")
            if answer.status:
                state.status = MachineStatus(answer.status)
            return False
        log.info("status %s -> %s", state.status, status)
        state.status = status
        return True

    async def machine_server_status(self) -> Message | None:
        """GET_STATUS: the Machine Server's view of the machine (None if it does not answer)."""
        try:
            return await self.host.ask(Conv.GET_STATUS, message(Msg.GET_STATUS, machine_id=self.state.machine_id), "ms")
        except ConversationTimeout:
            return None

    async def set_accept_types(self, op_types: list[str]) -> bool:
        """ACC_TYP_C to MSCHED. One change at a time, in the order asked: a later change (all operations
        after a run) never overtakes an earlier one still unanswered (a setup's none, asked in the
        background), which would leave MSCHED with the earlier."""
        async with self._accept_lock:
            return await self._set_accept_types(op_types)

    async def _set_accept_types(self, op_types: list[str]) -> bool:
        log = self.host.log
        try:
            answer = await self.host.ask(
                Conv.ACC_TYP_C,
                message(Msg.CHG_ACCEPT_TYPE, machine_id=self.state.machine_id, op_types=op_types),
                "msched",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            log.error("MSCHED did not answer the accept-type change to %s", op_types or "none")
            return False
        if answer.ack_code != AckCode.ACK_OK:
            log.error("MSCHED refused accept types %s: %s", op_types, answer.ack_code)
            return False
        log.info("accept types: %s", "all operations" if op_types == ALL_OPERATIONS else op_types or "none")
        return True

    async def accepted_none(self, run_id: int) -> None:
        """The run's setup asked MSCHED for accepts-nothing without waiting: its answer, now."""
        accepting, self.accepting_none = self.accepting_none, None
        if accepting is None:
            return
        try:
            accepted = await accepting
        except GwcError as e:
            accepted = False
            self.host.log.error("run %d: accept types none: %s", run_id, e)
        if not accepted:
            self.host.log.error("run %d: MSCHED did not take its setup's accept types none", run_id)

    # ----------------------------------------------------------------- the Cell Alarm Server

    async def raise_alarm(self, alarm_id: str, text: str, wait: bool, retry: bool | None = None) -> int | None:
        """6.3.2.8: pass an alarm to the CAS; when `wait`, hold until the operator clears it (wait_cleared).
        Its alarm number, or None if the CAS did not take it. A CAS that does not answer is asked again
        when `retry` (by default: when `wait`)."""
        log = self.host.log
        retry = wait if retry is None else retry
        while True:
            try:
                answer = await self.host.ask(
                    Conv.ALARM_SEND,
                    message(
                        Msg.ALARM_SEND,
                        alarm_id=alarm_id,
                        alarm_text=text,
                        machine_id=self.state.machine_id,
                        raised_by=self.host.name,
                    ),
                    "cas",
                    SERVER_TIMEOUT,
                )
                break
            except ConversationTimeout:
                if not retry:
                    log.error("Cell Alarm Server did not take alarm %s", alarm_id)
                    return None
                log.error("Cell Alarm Server did not take alarm %s: trying again", alarm_id)
        if answer.ack_code != AckCode.ACK_OK or answer.alarm_no is None:
            log.error("Cell Alarm Server refused alarm %s: %s", alarm_id, answer.ack_code)
            return None
        log.info("alarm %d (%s) raised: %s", answer.alarm_no, alarm_id, text)
        if wait:
            await self.wait_cleared(int(answer.alarm_no))
        return int(answer.alarm_no)

    async def wait_cleared(self, alarm_no: int) -> None:
        """Hold until alarm `alarm_no` is cleared (by the operator, or withdrawn by the WC itself)."""
        if alarm_no in self._cleared:
            return
        cleared = asyncio.get_running_loop().create_future()
        self._alarm_waits[alarm_no] = cleared
        self.host.log.info("alarm %d pending: waiting for the operator to clear it", alarm_no)
        try:
            await cleared
        finally:
            self._alarm_waits.pop(alarm_no, None)
        self.host.log.info("alarm %d cleared: continuing", alarm_no)

    def done_waiting(self, alarm_no: int) -> None:
        """Alarm `alarm_no` is cleared: whoever waits for it goes on."""
        self._cleared.add(alarm_no)
        waiter = self._alarm_waits.get(alarm_no)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def clear_alarm(self, alarm_no: int, cleared_by: str) -> Message | None:
        """ALARM_CLR_REQ: the WC clears an alarm of its own; the CAS's answer (None if it did not answer)."""
        try:
            return await self.host.ask(
                Conv.ALARM_CLR_REQ,
                message(Msg.ALARM_CLEAR_REQUEST, alarm_no=alarm_no, cleared_by=cleared_by),
                "cas",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            return None

    def alarm_text(self, alarm_id: str) -> str:
        """The alarm's text for the operator (ALARM_DESCRIPTION), named after the machine."""
        machine_id, log = self.state.machine_id, self.host.log
        try:
            row = self.read("SELECT alarm_text FROM alarm_description WHERE alarm_id = %s", (alarm_id,))
        except DatabaseError as e:
            log.error("cannot check alarm %s in ALARM_DESCRIPTION: %s", alarm_id, e)
            row = None
        if row is None:
            log.warning("alarm %s is not in ALARM_DESCRIPTION: passing it on as unknown", alarm_id)
            return f"unknown alarm {alarm_id} from {machine_id}"
        return f"{machine_id}: {row[0]}"

    # ----------------------------------------------------------------- the Equipment Recipe Server

    async def fetch_recipe(self, recipe_id: str) -> tuple[Path | None, str]:
        """The approved version from the ERS, checksum verified, written where the ME can read it."""
        state = self.state
        try:
            reply = await self.host.ask(
                Conv.RECIPE_GET,
                message(Msg.RECIPE_FETCH, recipe_id=recipe_id, machine_id=state.machine_id),
                "ers",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            return None, "the Equipment Recipe Server did not answer"
        if reply.ack_code != AckCode.ACK_OK or reply.content is None:
            return None, reply.note or f"recipe {recipe_id} refused by the ERS ({reply.ack_code})"
        digest = hashlib.sha256(reply.content.encode()).hexdigest()
        if digest != reply.checksum:
            return None, f"recipe {recipe_id} v{reply.version} checksum mismatch: the recipe was modified"
        path = state.recipe_file(recipe_id, reply.version)
        with contextlib.suppress(OSError, UnicodeDecodeError):
            if path.read_text() == reply.content:  # written by an earlier setup, as approved: a read, not a write
                return path, ""
        # Written whole, then renamed: the ME never reads half a recipe. Every fetch runs under the state
        # lock (SETUP_RUN, DNLD_ME), so one temporary name serves.
        tmp = path.with_name(f"{path.name}.tmp")
        try:
            state.recipe_dir.mkdir(parents=True, exist_ok=True)
            tmp.write_text(reply.content)
            tmp.replace(path)
        except OSError as e:
            with contextlib.suppress(OSError):
                tmp.unlink()
            return None, f"recipe {recipe_id} v{reply.version} not written to {path}: {e}"
        return path, ""

    async def store_recipe(self, recipe_id: str, content: str, by: str) -> Message | None:
        """RECIPE_PUT: the machine's copy of a recipe stored by the ERS (None if it did not answer)."""
        try:
            return await self.host.ask(
                Conv.RECIPE_PUT,
                message(Msg.RECIPE_STORE, recipe_id=recipe_id, content=content, by=by, description=None),
                "ers",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            return None
