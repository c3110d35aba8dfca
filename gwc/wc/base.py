"""The WC's state and what it asks of the cell's servers: status changes (Machine Server), accept types
(MSCHED), alarms (Cell Alarm Server) and its reads (see gwc/wc/wc.py)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from gwc.db import Statement
from gwc.errors import ConversationTimeout, DatabaseError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S, Module
from gwc.wc.link import MeLink

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
S = MachineStatus


class WCBase(Module):
    """The WC's state (set by WC.__init__) and its conversations with the servers."""

    status: MachineStatus  # our copy of MACHINE_STATUS.status; the Machine Server holds the truth
    machine_id: str
    machine_run_id: int | None
    recipe_id: str | None
    me: MeLink
    recipe_dir: Path
    results_dir: Path
    _state_lock: asyncio.Lock  # one status-changing step at a time
    _alarm_waits: dict[int, asyncio.Future[None]]
    _cleared: set[int]  # alarm numbers seen cleared (a clear may beat our wait for it)
    _alarm_pending: int  # alarms of ours waiting for the operator: ME answers may take that long
    _set_up_for: tuple[str, int] | None  # (asker, machine_run_id) of the last setup, its reservation checked
    _accept_lock: asyncio.Lock
    _accepting_none: asyncio.Future[bool] | None

    @property
    def _loop(self) -> asyncio.AbstractEventLoop:
        return self.bus.loop

    def _read_status(self) -> tuple[MachineStatus, int | None, str | None]:
        row = self._read(
            "SELECT status, machine_run_id, recipe_id FROM machine_status WHERE machine_id = %s", (self.machine_id,)
        )
        return (MachineStatus(row[0]), row[1], row[2]) if row else (S.SHUTDOWN, None, None)

    def _read(self, sql: str, params: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """One row read; DatabaseError if the database refuses it, DatabaseUnavailable if it is away."""
        return self.transaction(Statement(sql, params))

    async def _read_when_up(self, sql: str, params: tuple[Any, ...] | dict[str, Any]) -> tuple[Any, ...] | None:
        """One row read for a step a lot waits on: a database outage is waited out (DATABASE_OUTAGE_S)."""
        return await self.transaction_when_up(Statement(sql, params), DATABASE_OUTAGE_S)

    async def change_status(
        self, status: MachineStatus, expect: list[MachineStatus] | None = None, **fields: Any
    ) -> bool:
        """Ask the Machine Server to change our status; keep our copy in step when it agrees."""
        try:
            answer = await self.ask(
                Conv.CHG_STATUS,
                message(
                    Msg.CHANGE_STATUS,
                    machine_id=self.machine_id,
                    status=status,
                    expect=[str(s) for s in expect] if expect else None,
                    **fields,
                ),
                "ms",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            self.log.error("Machine Server did not answer the change to %s", status)
            return False
        # A refusal that names the status asked for is no refusal: asked again after the Machine
        # Server restarted, the first change had been made.
        if answer.ack_code != AckCode.ACK_OK and answer.status != status:
            self.log.error("Machine Server refused %s: %s %s", status, answer.ack_code, answer.note or "")
            if answer.status:
                self.status = MachineStatus(answer.status)
            return False
        self.log.info("status %s -> %s", self.status, status)
        self.status = status
        return True

    async def set_accept_types(self, op_types: list[str]) -> bool:
        """ACC_TYP_C to MSCHED. One change at a time, in the order asked: a later change (all operations
        after a run) never overtakes an earlier one still unanswered (a setup's none, asked in the
        background), which would leave MSCHED with the earlier."""
        async with self._accept_lock:
            return await self._set_accept_types(op_types)

    async def _set_accept_types(self, op_types: list[str]) -> bool:
        try:
            answer = await self.ask(
                Conv.ACC_TYP_C,
                message(Msg.CHG_ACCEPT_TYPE, machine_id=self.machine_id, op_types=op_types),
                "msched",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            self.log.error("MSCHED did not answer the accept-type change to %s", op_types or "none")
            return False
        if answer.ack_code != AckCode.ACK_OK:
            self.log.error("MSCHED refused accept types %s: %s", op_types, answer.ack_code)
            return False
        self.log.info("accept types: %s", "all operations" if op_types == ALL_OPERATIONS else op_types or "none")
        return True

    async def raise_alarm(self, alarm_id: str, text: str, wait: bool, retry: bool | None = None) -> int | None:
        """6.3.2.8: pass an alarm to the CAS; when `wait`, hold until the operator clears it (wait_cleared).
        Its alarm number, or None if the CAS did not take it. A CAS that does not answer is asked again
        when `retry` (by default: when `wait`)."""
        retry = wait if retry is None else retry
        while True:
            try:
                answer = await self.ask(
                    Conv.ALARM_SEND,
                    message(
                        Msg.ALARM_SEND,
                        alarm_id=alarm_id,
                        alarm_text=text,
                        machine_id=self.machine_id,
                        raised_by=self.name,
                    ),
                    "cas",
                    SERVER_TIMEOUT,
                )
                break
            except ConversationTimeout:
                if not retry:
                    self.log.error("Cell Alarm Server did not take alarm %s", alarm_id)
                    return None
                self.log.error("Cell Alarm Server did not take alarm %s: trying again", alarm_id)
        if answer.ack_code != AckCode.ACK_OK or answer.alarm_no is None:
            self.log.error("Cell Alarm Server refused alarm %s: %s", alarm_id, answer.ack_code)
            return None
        self.log.info("alarm %d (%s) raised: %s", answer.alarm_no, alarm_id, text)
        if wait:
            await self.wait_cleared(int(answer.alarm_no))
        return int(answer.alarm_no)

    async def wait_cleared(self, alarm_no: int) -> None:
        """Hold until alarm `alarm_no` is cleared (by the operator, or withdrawn by the WC itself)."""
        if alarm_no in self._cleared:
            return
        cleared = self._loop.create_future()
        self._alarm_waits[alarm_no] = cleared
        self.log.info("alarm %d pending: waiting for the operator to clear it", alarm_no)
        try:
            await cleared
        finally:
            self._alarm_waits.pop(alarm_no, None)
        self.log.info("alarm %d cleared: continuing", alarm_no)

    def _done_waiting(self, alarm_no: int) -> None:
        """Alarm `alarm_no` is cleared: whoever waits for it goes on."""
        self._cleared.add(alarm_no)
        waiter = self._alarm_waits.get(alarm_no)
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def alarm_cleared(self, conv: Conversation) -> None:
        assert conv.first is not None
        clear = conv.first.first
        if clear.machine_id not in (None, self.machine_id):
            return
        self._done_waiting(clear.alarm_no)

    def _alarm_text(self, alarm_id: str) -> str:
        try:
            row = self._read("SELECT alarm_text FROM alarm_description WHERE alarm_id = %s", (alarm_id,))
        except DatabaseError as e:
            self.log.error("cannot check alarm %s in ALARM_DESCRIPTION: %s", alarm_id, e)
            row = None
        if row is None:
            self.log.warning("alarm %s is not in ALARM_DESCRIPTION: passing it on as unknown", alarm_id)
            return f"unknown alarm {alarm_id} from {self.machine_id}"
        return f"{self.machine_id}: {row[0]}"
