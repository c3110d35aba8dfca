"""The operation entity and the Lot Server (LotServerLink): ENTITY_REQ (attach, moves, progress reports
sent in the background) and the wait for the operator's import or export (see gwc/lot/entity.py)."""

from __future__ import annotations

import concurrent.futures
import os
import time
from collections.abc import Sequence

from gwc.errors import GwcError
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, LotState
from gwc.ipc.names import Conv, Msg
from gwc.lot.core import Heard
from gwc.lot.errors import LotError, LotTimeout
from gwc.lot.model import ALREADY, POLL
from gwc.lot.state import EntityState
from gwc.lot.talk import BusLink
from gwc.retry import Deadline


class LotServerLink:
    """ENTITY_REQ to the Lot Server, and what it answers kept in the EntityState."""

    def __init__(self, facts: EntityState, heard: Heard, link: BusLink) -> None:
        self.facts = facts
        self.heard = heard
        self.link = link
        # Progress reports (waiting_machine, running) on their way to the Lot Server, in order (report()).
        self._reporter: concurrent.futures.ThreadPoolExecutor | None = None
        self._reports: list[concurrent.futures.Future[Message]] = []

    def open(self) -> None:
        """Start the reports' thread now, not at the first report: starting one takes milliseconds on a
        busy machine."""
        self._reporter = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"{self.facts.name}-reports")
        self._reporter.submit(lambda: None)

    def close(self) -> None:
        """A report still retrying fails fast once the bus is gone. Safe to call twice."""
        if self._reporter is not None:
            self._reporter.shutdown(wait=False, cancel_futures=True)
            self._reporter = None

    def entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
    ) -> Message:
        """ENTITY_REQ: ask the Lot Server to move this entity (import, export, completed, failed ...).

        Asked again while the Lot Server is away or not started (see BusLink.ask). Every action is safe
        to repeat: the Lot Server moves an entity only into the state it is asked for (attach, completed,
        failed, waiting_machine, running: a repeat finds it there and changes nothing), and a repeated
        import or export that finds the operator already moved the entity on is taken as done (ALREADY).
        Progress reports sent before (report()) are answered first; one that failed raises here.
        """
        self.drain_reports()
        return self._entity_request(action, reason, script_pid, timeout, within)

    def attach(self) -> Message:
        """ENTITY_REQ attach: the Lot Server records our pid and answers with the entity's state, its lot
        and its lot script (the lot's own, else its product's; None if neither names one)."""
        facts = self.facts
        try:
            ack = self.entity_request("attach", script_pid=os.getpid())
        except LotTimeout:
            raise
        except LotError:
            facts.failed = True  # refused (unknown, failed or exported): nothing of ours to clean up
            raise
        facts.product_id, facts.priority, facts.work_order_id = ack.product_id, ack.priority, ack.work_order_id
        facts.script_id, facts.script_path = ack.script_id, ack.script_path
        return ack

    def read_state(self) -> str | None:
        """The entity's state as the Lot Server has it, asked once (None if it has none for the entity or
        does not answer now): the fallback of a wait for a broadcast that may have been missed."""
        try:
            state = self._entity_request("state", within=0, keep_state=True).state
        except GwcError as e:
            self.facts.log.warning("entity %d: state not read from the Lot Server: %s", self.facts.entity_id, e)
            return None
        return None if state is None else str(state)

    def wait_moved(self, action: str, states: Sequence[str], timeout: float) -> None:
        """Wait for LOT_MOVED(action) for this entity, asking the Lot Server for its state as a fallback
        every POLL seconds (not at every wake-up: every machine's news wakes a lot in the cell)."""
        deadline = Deadline(timeout)
        heard = self.heard
        while True:
            next_poll = time.monotonic() + POLL
            with heard.cond:
                while True:
                    for act, lot_id in heard.moved:
                        if act == action:
                            if lot_id is not None:
                                self.facts.lot_id = lot_id
                            return
                    left = min(next_poll - time.monotonic(), deadline.left())
                    if left <= 0:
                        break
                    heard.cond.wait(left)
            state = self.read_state()
            if state in states:
                return
            if state == LotState.FAILED:
                raise LotError(f"entity {self.facts.entity_id} was marked failed while waiting for {action}")
            if deadline.expired:
                raise LotTimeout(
                    f"entity {self.facts.entity_id}: the operator did not {action} the lot within "
                    f"{timeout:.0f}s (it is {state})"
                )

    def report(self, action: str) -> None:
        """ENTITY_REQ for a progress state (waiting_machine, running), sent without waiting for the answer.

        The Lot Server records progress for the operator; the operation does not need its answer, so
        reports go in the background, one at a time and in order (asked again while the Lot Server is
        away, as entity_request is), and the next entity_request waits for them first. A report the
        Lot Server refuses raises there, at the latest when the lot completes or fails.
        """
        self.facts.set_state(action)
        if self._reporter is None:
            raise LotError(f"entity {self.facts.entity_id} is not open")
        self._reports.append(self._reporter.submit(self._entity_request, action, keep_state=True))

    def drain_reports(self) -> None:
        """Wait for the reports sent; one the Lot Server refused raises."""
        reports, self._reports = self._reports, []
        for report in reports:
            report.result()

    def _entity_request(
        self,
        action: str,
        reason: str | None = None,
        script_pid: int | None = None,
        timeout: float | None = None,
        within: float | None = None,
        keep_state: bool = False,
    ) -> Message:
        facts = self.facts
        ack = self.link.ask(
            Conv.ENTITY_REQ,
            message(Msg.ENTITY_REQUEST, entity_id=facts.entity_id, action=action, reason=reason, script_pid=script_pid),
            "ls",
            timeout,
            within,
        )
        if ack.ack_code == AckCode.NOTNOW and ack.state in ALREADY.get(action, ()):
            facts.log.info("entity %d: %s already done (the entity is %s)", facts.entity_id, action, ack.state)
        elif ack.ack_code != AckCode.ACK_OK:
            raise LotError(
                f"the Lot Server refused {action} for entity {facts.entity_id}: {ack.ack_code}"
                + (f" ({ack.note})" if ack.note else "")
                + (f", entity is {ack.state}" if ack.state else "")
            )
        if ack.lot_id is not None:
            facts.lot_id = ack.lot_id
        if ack.state and not keep_state:  # a report's answer comes after the script has moved on
            facts.set_state(ack.state)
        return ack
