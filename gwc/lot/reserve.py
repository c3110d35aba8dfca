"""The operation entity and MSCHED (MachineRequests): requesting machines (with alternatives), waiting
for them, cancelling requests and giving machines back (see gwc/lot/entity.py, docs/lot-scripts.md)."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable, Sequence

from gwc.errors import ConversationTimeout, GwcError
from gwc.ipc.bus import Batch, Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, LotState
from gwc.ipc.names import Conv, Msg
from gwc.lot.core import Heard, LotReads
from gwc.lot.errors import LotError, LotTimeout, RequestCancelled, RequestRefused
from gwc.lot.lot_server import LotServerLink
from gwc.lot.model import BOUND_AT_ONCE, FOREVER, POLL, UP, Alternative, MachineRequest, Reservation
from gwc.lot.state import EntityState
from gwc.lot.talk import BusLink
from gwc.module import ask_again
from gwc.retry import Deadline


class MachineRequests:
    """MACH_REQ, CANCEL_RE and UNRESERVE as the lot script's steps."""

    def __init__(self, facts: EntityState, reads: LotReads, heard: Heard, link: BusLink, ls: LotServerLink) -> None:
        self.facts = facts
        self.reads = reads
        self.heard = heard
        self.link = link
        self.ls = ls
        self._requests: list[MachineRequest] = []  # asked for and not yet waited for
        self._asked: list[MachineRequest] = []  # every request this process made
        self._groups = 0

    def qualified_machines(self, op_type: str, up_only: bool = True) -> list[str]:
        """Machines with a recipe for op_type (OP_MACHINE_RECIPE), those that are up if `up_only`."""
        sql = (
            "SELECT DISTINCT r.machine_id FROM op_machine_recipe r JOIN machine_status s USING (machine_id) "
            "WHERE r.op_type = %s" + (" AND s.status = ANY(%s)" if up_only else "") + " ORDER BY 1"
        )
        rows = self.reads.query(sql, op_type, *([list(UP)] if up_only else []))
        return [r[0] for r in rows]

    def request_machines(
        self, op_type: str, alternatives: Sequence[Sequence[str]], priority: int | None = None
    ) -> MachineRequest:
        """MACH_REQ: one request per alternative (all machines of an alternative are needed).

        Returns once MSCHED acknowledged each (queued with a request_key, or NO_MACHINE). All of them
        carry one new alt_group, so MSCHED binds at most one: a sibling that reaches it after another
        was bound is refused (Machine_Req_Ack REQ_CANCEL), which the entity takes as a sibling cancel.
        """
        alts = [Alternative(op_type, list(a)) for a in alternatives if a]
        if not alts:
            raise RequestRefused(f"no machines to ask for {op_type}")
        self.link.listen_in_cell()  # already, unless the script skipped wait_for_import
        self._groups += 1  # unique per call (and per process: a restarted script's groups are new ones)
        request = MachineRequest(op_type, alts, f"{self.facts.entity_id}.{os.getpid()}.{self._groups}")
        self._requests.append(request)
        self._asked.append(request)
        for alt in alts:
            self.link.spawn(self._request(alt, priority if priority is not None else self.facts.priority))
        self.heard.wait(
            lambda: all(a.ack is not None or a.done for a in alts),
            self.facts.timeouts.retry + self.facts.timeouts.answer + 1,
            f"MSCHED's answer to the request for {op_type}",
        )
        for a in alts:
            if a.ack is not None and a.ack.ack_code == AckCode.ACK_OK:
                self.facts.log.info("request %s for %s (%s) queued", a.key, op_type, a.describe())
            elif a.sibling_cancelled:
                self.facts.log.info(
                    "request for %s (%s) not queued: another alternative is bound", op_type, a.describe()
                )
            else:
                self.facts.log.warning(
                    "request for %s (%s) refused: %s",
                    op_type,
                    a.describe(),
                    a.error or (a.ack.ack_code if a.ack else "no answer"),
                )
        return request

    def wait_for_machines(self, request: MachineRequest, timeout: float | None = None) -> Reservation:
        """Wait for MSCHED to bind one alternative (Machine_Req_Comp ACK_OK): machines and machine_run_id."""
        timeout = timeout or self.facts.timeouts.machines
        alts = request.alternatives

        surplus: list[str] = []

        def outcome() -> Alternative | Reservation | bool:
            if request.found is not None:
                return request.found
            bound = [a for a in alts if a.comp is not None and a.comp.ack_code == AckCode.ACK_OK]
            if bound:
                request.winner = bound[0]
                surplus.extend(m for a in bound[1:] for m in request.surplus(a))
                return bound[0]
            return all(a.done for a in alts) and not any(a.sibling_cancelled for a in alts)

        try:
            with self.heard.cond:  # MSCHED's Machine_Req_Comp follows its Machine_Req_Ack when it binds at once
                got = self.heard.cond.wait_for(outcome, BOUND_AT_ONCE)
            if not got and self.facts.state != LotState.WAITING_MACHINE:  # not bound at once: it waits, say so
                self.ls.report(LotState.WAITING_MACHINE)
            got = got or self.heard.wait(  # type: ignore[assignment]  # T is the union outcome() returns
                outcome,
                timeout,
                f"machines for {request.op_type} ({request.describe()})",
                poll=lambda: self._bound_unheard(request),
            )
        finally:
            if request in self._requests:
                self._requests.remove(request)
        for m in surplus:  # MSCHED bound two alternatives: keep the first, give the other back
            self.facts.log.warning("%s was bound too by another alternative: giving it back", m)
            self.unreserve(m)
        if isinstance(got, Reservation):
            self.ls.report(LotState.RUNNING)
            return got
        if isinstance(got, Alternative):
            if any(not a.done for a in alts if a is not got):  # a sibling may still be queued: end it
                self.cancel_leftovers("after taking an alternative", request)
            assert got.comp is not None
            res = Reservation(request.op_type, int(got.comp.machine_run_id or 0), got.key, got.reserved or got.machines)
            self.facts.log.info(
                "got machine_run_id %d on %s for %s (request %s)",
                res.machine_run_id,
                ", ".join(res.machines),
                res.op_type,
                res.request_key,
            )
            self.ls.report(LotState.RUNNING)
            return res
        cancelled = [a for a in alts if a.comp is not None and a.comp.ack_code == AckCode.REQ_CANCEL]
        if cancelled:
            notes = "; ".join(f"request {a.key}: {a.comp.note or 'cancelled'}" for a in cancelled if a.comp)
            self.facts.log.error("machine request for %s cancelled (REQ_CANCEL): %s", request.op_type, notes)
            raise RequestCancelled(f"machine request for {request.op_type} was cancelled (REQ_CANCEL): {notes}")
        errors = [a.error for a in alts if a.error]
        if errors:
            raise LotError(f"machine request for {request.op_type} failed: {'; '.join(errors)}")
        codes = sorted({answer.ack_code for a in alts if (answer := a.comp or a.ack) is not None})
        raise RequestRefused(f"no machine for {request.op_type} ({request.describe()}): {', '.join(codes)}")

    def _bound_unheard(self, request: MachineRequest) -> None:
        """(the wait's fallback read) Every alternative was refused because one of its group is bound, yet
        no binding was heard: MSCHED bound it in a conversation the entity had given up (asked again after
        a restarting MSCHED's Notnow). The binding is in SATISFIED_ALT_GROUPS and RESERVED_MACHINES."""
        if request.alt_group is None or not all(a.sibling_cancelled for a in request.alternatives):
            return
        rows = self.reads.query(
            "SELECT r.machine_id, r.machine_run_id, r.request_key FROM satisfied_alt_groups g "
            "JOIN reserved_machines r ON r.entity_id = g.entity_id AND r.request_key = g.request_key "
            "WHERE g.entity_id = %s AND g.alt_group = %s ORDER BY r.machine_id",
            self.facts.entity_id,
            request.alt_group,
            within=0,
        )
        if rows:
            found = Reservation(request.op_type, int(rows[0][1]), int(rows[0][2]), [str(r[0]) for r in rows])
            self.link.watch(found.machines)
            self.facts.log.warning(
                "request %s was bound unheard (its conversation given up): %s", found.request_key, found
            )
            with self.heard.cond:
                request.found = found
                self.heard.cond.notify_all()

    def reserve(
        self,
        op_type: str,
        alternatives: Sequence[Sequence[str]] | None = None,
        priority: int | None = None,
        timeout: float | None = None,
    ) -> Reservation:
        """Request machines and wait for them; when none can serve now, wait for one to come up and ask again.

        Without alternatives, each machine qualified for op_type that is up is one alternative.
        """
        deadline = Deadline(timeout or self.facts.timeouts.machines)
        for attempt in range(1, self.facts.max_tries + 1):
            alts = [list(a) for a in alternatives] if alternatives else [[m] for m in self.qualified_machines(op_type)]
            try:
                if alts:
                    request = self.request_machines(op_type, alts, priority)
                    return self.wait_for_machines(request, max(0.1, deadline.left()))
                reason = f"no machine qualified for {op_type} is up"
            except RequestRefused as e:
                reason = str(e)
            if attempt == self.facts.max_tries:
                raise RequestRefused(f"{reason} (asked {attempt} times)")
            self.facts.log.warning("%s: waiting for a machine to come up, then asking again", reason)
            self.pause(attempt, f"asking MSCHED for {op_type} again")
            self.wait_machine_up(op_type, alternatives, deadline)
        raise AssertionError("unreachable")

    def cancel_requests(
        self, request_key: int | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """CANCEL_RE: cancel one request, or all of the entity's. Returns how many were cancelled."""
        ack = self.link.ask(
            Conv.CANCEL_RE,
            message(
                Msg.CANCEL_REQUEST,
                request_key=request_key,
                entity_id=None if request_key else self.facts.entity_id,
                by=self.facts.name,
            ),
            "msched",
            timeout,
            within,
        )
        if ack.ack_code not in (AckCode.ACK_OK, AckCode.REQ_KEY_U):
            raise LotError(f"MSCHED refused to cancel the requests of entity {self.facts.entity_id}: {ack.ack_code}")
        return int(ack.cancelled or 0)

    def unreserve(
        self, machine_id: str | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """UNRESERVE: free one reserved machine, or all of the entity's. Returns how many were freed."""
        return self.unreserve_soon(machine_id, timeout, within)()

    def unreserve_soon(
        self, machine_id: str | None = None, timeout: float | None = None, within: float | None = None
    ) -> Callable[[], int]:
        """unreserve() sent now; the function returned waits for MSCHED's answer (how many were freed),
        so that the script can work while MSCHED frees the machines. Call it."""
        self.link.unwatch(machine_id)  # its news is no business of the entity's any more
        asked = self.link.ask_soon(
            Conv.UNRESERVE,
            message(Msg.UNRESERVE_ME, entity_id=self.facts.entity_id, machine_id=machine_id, by=self.facts.name),
            "msched",
            timeout,
            within,
        )

        def freed() -> int:
            ack = asked()
            if ack.ack_code == AckCode.NOT_RESERVED:
                self.facts.log.info("unreserve %s: nothing reserved", machine_id or "all")
                return 0
            if ack.ack_code != AckCode.ACK_OK:
                raise LotError(
                    f"MSCHED refused to unreserve {machine_id or 'the machines'} of entity {self.facts.entity_id}: "
                    f"{ack.ack_code}"
                )
            self.facts.log.info("unreserved %s (%s freed)", machine_id or "all machines", ack.freed)
            return int(ack.freed or 0)

        return freed

    def may_be_queued(self) -> bool:
        """Whether a request this process made may still wait in MSCHED's queue: an alternative whose end
        MSCHED has not told (no Machine_Req_Comp, no refusal yet, or its conversation lost to an error)."""
        return any(not a.done or a.error is not None for r in self._asked for a in r.alternatives)

    def cancel_leftovers(self, when: str, request: MachineRequest | None = None) -> None:
        """Cancel the entity's requests still queued in MSCHED (all of them, or only `request`'s when
        another request of the entity is still being asked for). Belt and braces: a failure is logged."""
        try:
            if request is not None and any(r is not request for r in self._requests):
                n = sum(
                    self.cancel_requests(a.key, within=self.facts.timeouts.cleanup)
                    for a in request.alternatives
                    if a.key is not None and not a.done and a is not request.winner
                )
            else:
                n = self.cancel_requests(within=self.facts.timeouts.cleanup)
        except GwcError as e:
            self.facts.log.warning("could not cancel the requests left %s: %s", when, e)
            return
        if n:
            self.facts.log.info("cancelled %d request(s) of entity %d left queued %s", n, self.facts.entity_id, when)

    def wait_machine_up(self, op_type: str, alternatives: Sequence[Sequence[str]] | None, deadline: Deadline) -> None:
        """Until a machine can serve the operation again: every machine of one alternative is up (without
        alternatives: one machine qualified for op_type is)."""
        while not deadline.expired:
            if alternatives:
                up = {
                    r[0]
                    for r in self.reads.query("SELECT machine_id FROM machine_status WHERE status = ANY(%s)", list(UP))
                }
                if any(a and set(a) <= up for a in alternatives):
                    return
            elif self.qualified_machines(op_type):
                return
            with self.heard.cond:
                self.heard.cond.wait(min(POLL, deadline.left()))
        raise LotTimeout(f"entity {self.facts.entity_id}: no machine for {op_type} came up in time")

    def pause(self, tries: int, what: str) -> None:
        """The pause before an operation's next try: a machine that just failed gets time to be marked
        down (or come up) rather than be asked again at once."""
        pause = self.facts.timeouts.pause * 2 ** (tries - 1)
        self.facts.log.info("%s in %.1fs", what, pause)
        time.sleep(pause)

    # ----------------------------------------------------------------- MACH_REQ

    async def _request(self, alt: Alternative, priority: int | None) -> None:
        """One MACH_REQ conversation, from Machine_Request to its one Machine_Req_Comp.

        Until MSCHED takes it (Machine_Req_Ack), a MSCHED away, not started or silent is asked again
        in a new conversation, as `_ask` does: a request that did reach it and is asked again is one
        more alternative of the same alt_group, which MSCHED refuses once one is bound, and which the
        entity cancels once it has its machines.
        """
        bus = self.link.need().bus
        group = alt.group
        conv: Conversation | None = None
        backoff = self.facts.timeouts.asking()
        try:
            while alt.ack is None and not alt.done:
                if group is not None and group.winner is not None:  # no need to ask any more
                    with self.heard.cond:
                        alt.done = True
                        self.heard.cond.notify_all()
                    return
                if not self.link.present("msched"):
                    why = "msched is not on the bus"
                else:
                    conv = await bus.start(
                        Conv.MACH_REQ,
                        message(
                            Msg.MACHINE_REQUEST,
                            entity_id=self.facts.entity_id,
                            op_type=alt.op_type,
                            num_machines=len(alt.machines),
                            priority=priority,
                            alt_group=group.alt_group if group else None,
                        ),
                        *[message(Msg.MACHINE_ENTRY, machine_id=m) for m in alt.machines],
                        to="msched",
                    )
                    try:
                        batch = await conv.next_message(self.facts.timeouts.answer)
                    except ConversationTimeout:
                        why = f"no answer within {self.facts.timeouts.answer:.1f}s"
                    else:
                        if not ask_again(batch.first):
                            await self._answered(alt, conv, batch)
                            continue
                        why = f"msched cannot answer now ({batch.first.ack_code} {batch.first.note or ''})"
                    conv.end()
                    conv = None
                pause = backoff.next()
                if pause is None:
                    raise LotTimeout(
                        f"MACH_REQ for {alt.op_type} ({alt.describe()}): {why} (asked {backoff.tries} times)"
                    )
                self.facts.log.warning(
                    "MACH_REQ for %s (%s): %s; asking again in %.1fs", alt.op_type, alt.describe(), why, pause
                )
                await asyncio.sleep(pause)
            while not alt.done:
                assert conv is not None
                await self._answered(alt, conv, await conv.next_message(FOREVER))
        except asyncio.CancelledError:
            raise
        except (GwcError, OSError) as e:
            with self.heard.cond:
                alt.error = str(e)
                alt.done = True
                self.heard.cond.notify_all()
        finally:
            if conv is not None:
                conv.end()

    async def _answered(self, alt: Alternative, conv: Conversation, batch: Batch) -> None:
        """MSCHED's Machine_Req_Ack or Machine_Req_Comp for one alternative."""
        head = batch.first
        if head.name == Msg.MACHINE_REQ_COMP:
            await conv.send(message(Msg.REQUEST_COMP_ACK, entity_id=self.facts.entity_id, ack_code=AckCode.ACK_OK))
        with self.heard.cond:
            if head.name == Msg.MACHINE_REQ_ACK:
                alt.ack = head
                alt.done = head.ack_code != AckCode.ACK_OK
            elif head.name == Msg.MACHINE_REQ_COMP:
                alt.comp = head
                alt.reserved = [m.machine_id for m in batch.messages[1:] if m.name == Msg.RESERVED_MACHINE]
                alt.done = True
            taken = alt.group is not None and alt.group.winner not in (None, alt) and head.ack_code == AckCode.ACK_OK
            surplus = alt.group.surplus(alt) if taken and alt.group and head.name == Msg.MACHINE_REQ_COMP else []
            queued = taken and head.name == Msg.MACHINE_REQ_ACK
            self.heard.cond.notify_all()
        if head.name == Msg.MACHINE_REQ_COMP and head.ack_code == AckCode.ACK_OK:
            # In this same turn of the bus's loop: whatever the script sends to the machines once woken is
            # sent after it, so no news of a machine it sets up can come before its filter hears them.
            self.link.watch([m.machine_id for m in batch.messages[1:] if m.name == Msg.RESERVED_MACHINE])
        for m in surplus:  # bound after the entity took another alternative: give it back
            self.facts.log.warning("%s was bound after another alternative was taken: giving it back", m)
            self.link.unwatch(m)
            await self._tell(
                Conv.UNRESERVE,
                message(Msg.UNRESERVE_ME, entity_id=self.facts.entity_id, machine_id=m, by=self.facts.name),
            )
        if queued:  # queued after the entity took another alternative: it must not wait there
            self.facts.log.warning("request %s was queued after another alternative was taken: cancelling it", alt.key)
            await self._tell(Conv.CANCEL_RE, message(Msg.CANCEL_REQUEST, request_key=alt.key, by=self.facts.name))

    async def _tell(self, cls: str, first: Message) -> None:
        """(bus thread) A cleanup conversation with MSCHED whose answer only goes to the log."""
        try:
            conv, batch = await self.link.need().bus.request(
                cls, first, to="msched", timeout=self.facts.timeouts.answer
            )
            conv.end()
            self.facts.log.info("%s: %s", cls, batch.first.ack_code)
        except GwcError as e:
            self.facts.log.error("%s failed: %s", cls, e)
