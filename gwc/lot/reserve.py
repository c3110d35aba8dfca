"""The operation entity and MSCHED: requesting machines (with alternatives), waiting for them, cancelling
requests and giving machines back (see gwc/lot/entity.py, docs/lot-scripts.md)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence

from gwc.errors import GwcError
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.lot.errors import LotError, LotTimeout, RequestCancelled, RequestRefused
from gwc.lot.events import Phase, event
from gwc.lot.model import BOUND_AT_ONCE, POLL, UP, Alternative, MachineRequest, Reservation, S
from gwc.lot.talk import EntityTalk


class EntityReserve(EntityTalk):
    """MACH_REQ, CANCEL_RE and UNRESERVE as the lot script's steps."""

    def qualified_machines(self, op_type: str, up_only: bool = True) -> list[str]:
        """Machines with a recipe for op_type (OP_MACHINE_RECIPE), those that are up if `up_only`."""
        sql = (
            "SELECT DISTINCT r.machine_id FROM op_machine_recipe r JOIN machine_status s USING (machine_id) "
            "WHERE r.op_type = %s" + (" AND s.status = ANY(%s)" if up_only else "") + " ORDER BY 1"
        )
        rows = self._query(sql, op_type, *([list(UP)] if up_only else []))
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
        self._listen_in_cell()  # already, unless the script skipped wait_for_import
        self._groups += 1  # unique per call (and per process: a restarted script's groups are new ones)
        request = MachineRequest(op_type, alts, f"{self.entity_id}.{os.getpid()}.{self._groups}")
        self._requests.append(request)
        self._asked.append(request)
        for alt in alts:
            self._spawn(self._request(alt, priority if priority is not None else self.priority))
        self._wait(
            lambda: all(a.ack is not None or a.done for a in alts),
            self.timeouts.retry + self.timeouts.answer + 1,
            f"MSCHED's answer to the request for {op_type}",
        )
        for a in alts:
            if a.ack is not None and a.ack.ack_code == AckCode.ACK_OK:
                self.log.info("request %s for %s (%s) queued", a.key, op_type, a.describe(), extra=event(Phase.QUEUED))
            elif a.sibling_cancelled:
                self.log.info("request for %s (%s) not queued: another alternative is bound", op_type, a.describe())
            else:
                self.log.warning(
                    "request for %s (%s) refused: %s",
                    op_type,
                    a.describe(),
                    a.error or (a.ack.ack_code if a.ack else "no answer"),
                )
        return request

    def wait_for_machines(self, request: MachineRequest, timeout: float | None = None) -> Reservation:
        """Wait for MSCHED to bind one alternative (Machine_Req_Comp ACK_OK): machines and machine_run_id."""
        timeout = timeout or self.timeouts.machines
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
            with self._cond:  # MSCHED's Machine_Req_Comp follows its Machine_Req_Ack when it binds at once
                got = self._cond.wait_for(outcome, BOUND_AT_ONCE)
            if not got and self.state != S.WAITING_MACHINE:  # not bound at once: it waits, say so
                self.report(S.WAITING_MACHINE)
            got = got or self._wait(  # type: ignore[assignment]  # T is the union outcome() returns
                outcome,
                timeout,
                f"machines for {request.op_type} ({request.describe()})",
                poll=lambda: self._bound_unheard(request),
            )
        finally:
            if request in self._requests:
                self._requests.remove(request)
        for m in surplus:  # MSCHED bound two alternatives: keep the first, give the other back
            self.log.warning("%s was bound too by another alternative: giving it back", m)
            self.unreserve(m)
        if isinstance(got, Reservation):
            self.report(S.RUNNING)
            return got
        if isinstance(got, Alternative):
            if any(not a.done for a in alts if a is not got):  # a sibling may still be queued: end it
                self._cancel_leftovers("after taking an alternative", request)
            assert got.comp is not None
            res = Reservation(request.op_type, int(got.comp.machine_run_id or 0), got.key, got.reserved or got.machines)
            self.log.info(
                "got machine_run_id %d on %s for %s (request %s)",
                res.machine_run_id,
                ", ".join(res.machines),
                res.op_type,
                res.request_key,
                extra=event(Phase.BOUND, res.machines[0] if res.machines else None),
            )
            self.report(S.RUNNING)
            return res
        cancelled = [a for a in alts if a.comp is not None and a.comp.ack_code == AckCode.REQ_CANCEL]
        if cancelled:
            notes = "; ".join(f"request {a.key}: {a.comp.note or 'cancelled'}" for a in cancelled if a.comp)
            self.log.error("machine request for %s cancelled (REQ_CANCEL): %s", request.op_type, notes)
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
        rows = self._query(
            "SELECT r.machine_id, r.machine_run_id, r.request_key FROM satisfied_alt_groups g "
            "JOIN reserved_machines r ON r.entity_id = g.entity_id AND r.request_key = g.request_key "
            "WHERE g.entity_id = %s AND g.alt_group = %s ORDER BY r.machine_id",
            self.entity_id,
            request.alt_group,
            within=0,
        )
        if rows:
            found = Reservation(request.op_type, int(rows[0][1]), int(rows[0][2]), [str(r[0]) for r in rows])
            self._watch(found.machines)
            self.log.warning("request %s was bound unheard (its conversation given up): %s", found.request_key, found)
            with self._cond:
                request.found = found
                self._cond.notify_all()

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
        deadline = time.monotonic() + (timeout or self.timeouts.machines)
        for attempt in range(1, self.max_tries + 1):
            alts = [list(a) for a in alternatives] if alternatives else [[m] for m in self.qualified_machines(op_type)]
            try:
                if alts:
                    request = self.request_machines(op_type, alts, priority)
                    return self.wait_for_machines(request, max(0.1, deadline - time.monotonic()))
                reason = f"no machine qualified for {op_type} is up"
            except RequestRefused as e:
                reason = str(e)
            if attempt == self.max_tries:
                raise RequestRefused(f"{reason} (asked {attempt} times)")
            self.log.warning("%s: waiting for a machine to come up, then asking again", reason)
            self._pause(attempt, f"asking MSCHED for {op_type} again")
            self._wait_machine_up(op_type, alternatives, deadline)
        raise AssertionError("unreachable")

    def cancel_requests(
        self, request_key: int | None = None, timeout: float | None = None, within: float | None = None
    ) -> int:
        """CANCEL_RE: cancel one request, or all of the entity's. Returns how many were cancelled."""
        ack = self._ask(
            Conv.CANCEL_RE,
            message(
                Msg.CANCEL_REQUEST,
                request_key=request_key,
                entity_id=None if request_key else self.entity_id,
                by=self.name,
            ),
            "msched",
            timeout,
            within,
        )
        if ack.ack_code not in (AckCode.ACK_OK, AckCode.REQ_KEY_U):
            raise LotError(f"MSCHED refused to cancel the requests of entity {self.entity_id}: {ack.ack_code}")
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
        self._unwatch(machine_id)  # its news is no business of the entity's any more
        asked = self._ask_soon(
            Conv.UNRESERVE,
            message(Msg.UNRESERVE_ME, entity_id=self.entity_id, machine_id=machine_id, by=self.name),
            "msched",
            timeout,
            within,
        )

        def freed() -> int:
            ack = asked()
            if ack.ack_code == AckCode.NOT_RESERVED:
                self.log.info("unreserve %s: nothing reserved", machine_id or "all")
                return 0
            if ack.ack_code != AckCode.ACK_OK:
                raise LotError(
                    f"MSCHED refused to unreserve {machine_id or 'the machines'} of entity {self.entity_id}: "
                    f"{ack.ack_code}"
                )
            self.log.info(
                "unreserved %s (%s freed)", machine_id or "all machines", ack.freed, extra=event(Phase.UNRESERVED)
            )
            return int(ack.freed or 0)

        return freed

    def _may_be_queued(self) -> bool:
        """Whether a request this process made may still wait in MSCHED's queue: an alternative whose end
        MSCHED has not told (no Machine_Req_Comp, no refusal yet, or its conversation lost to an error)."""
        return any(not a.done or a.error is not None for r in self._asked for a in r.alternatives)

    def _cancel_leftovers(self, when: str, request: MachineRequest | None = None) -> None:
        """Cancel the entity's requests still queued in MSCHED (all of them, or only `request`'s when
        another request of the entity is still being asked for). Belt and braces: a failure is logged."""
        try:
            if request is not None and any(r is not request for r in self._requests):
                n = sum(
                    self.cancel_requests(a.key, within=self.timeouts.cleanup)
                    for a in request.alternatives
                    if a.key is not None and not a.done and a is not request.winner
                )
            else:
                n = self.cancel_requests(within=self.timeouts.cleanup)
        except GwcError as e:
            self.log.warning("could not cancel the requests left %s: %s", when, e)
            return
        if n:
            self.log.info("cancelled %d request(s) of entity %d left queued %s", n, self.entity_id, when)

    def _wait_machine_up(self, op_type: str, alternatives: Sequence[Sequence[str]] | None, deadline: float) -> None:
        """Until a machine can serve the operation again: every machine of one alternative is up (without
        alternatives: one machine qualified for op_type is)."""
        while time.monotonic() < deadline:
            if alternatives:
                up = {
                    r[0] for r in self._query("SELECT machine_id FROM machine_status WHERE status = ANY(%s)", list(UP))
                }
                if any(a and set(a) <= up for a in alternatives):
                    return
            elif self.qualified_machines(op_type):
                return
            with self._cond:
                self._cond.wait(min(POLL, max(0.0, deadline - time.monotonic())))
        raise LotTimeout(f"entity {self.entity_id}: no machine for {op_type} came up in time")
