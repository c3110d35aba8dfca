"""The Machine Server (thesis 1.4.2): the one writer of MACHINE_STATUS.

It keeps every machine's status (Shutdown, Idle, Setup, Running, Setup_Shut, Run_Shut) with its
recipe, machine_run_id, start and end time and note; it changes a status only when asked
(CHG_STATUS), only along the transitions of 6.3.2 and only if the status is still the one the
asker expects, so two askers can never both win a race; and it broadcasts every change as
Update_ME_Status, so MSCHED and the operator learn of it without polling.

It also watches that each machine's WC is alive: a WC beats on the bus every heartbeat; one silent
longer than its machine's me_config.liveness_s while the machine is not Shutdown cannot be heard
(dead on a host without an agent, frozen, or cut off), so the machine is set Shutdown, the change
broadcast (MSCHED then routes around it) and alarm WC_SILENT raised. Where an agent runs, a death
is known at once: an ME's death (MOD_DIED) shuts its machine down then and there. Only MSCHED
touches reservations.

And it keeps the machines' books (1.4.2): every Run_Complete counts a run since maintenance; a
part a lot's verdict scraps (SCRAP_RPT, from the lot script) counts as the machine's scrap; when the
runs reach the machine's maintenance_every (cell.toml `maintenance_every`), alarm MAINT_DUE. MAINT_DONE,
the operator's word that the machine was maintained (`gwc machine maintenance-done`), starts the
count again.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from gwc.config import Config, RecordConfig
from gwc.errors import Refused
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S, Handler, Module
from gwc.record.calendar import is_planned
from gwc.servers import machine_store
from gwc.servers.common import Pruner, Server

# 6.3.2: where each status may go. Shutdown is always reachable (operator, ME death, liveness).
TRANSITIONS: dict[MachineStatus, frozenset[MachineStatus]] = {
    MachineStatus.SHUTDOWN: frozenset({MachineStatus.SHUTDOWN, MachineStatus.IDLE}),
    MachineStatus.IDLE: frozenset({MachineStatus.IDLE, MachineStatus.SETUP, MachineStatus.SHUTDOWN}),
    MachineStatus.SETUP: frozenset(
        {
            MachineStatus.SETUP,
            MachineStatus.IDLE,
            MachineStatus.RUNNING,
            MachineStatus.SETUP_SHUT,
            MachineStatus.SHUTDOWN,
        }
    ),
    MachineStatus.SETUP_SHUT: frozenset({MachineStatus.SETUP_SHUT, MachineStatus.RUN_SHUT, MachineStatus.SHUTDOWN}),
    MachineStatus.RUNNING: frozenset(
        {MachineStatus.RUNNING, MachineStatus.IDLE, MachineStatus.RUN_SHUT, MachineStatus.SHUTDOWN}
    ),
    MachineStatus.RUN_SHUT: frozenset({MachineStatus.RUN_SHUT, MachineStatus.SHUTDOWN}),
}
RUNNING = (MachineStatus.RUNNING, MachineStatus.RUN_SHUT)


@dataclass
class _Watch:
    """What the liveness watch knows of one machine."""

    status: MachineStatus
    liveness: float
    last_seen: float  # monotonic time its WC was last heard (or the watch began)


def stop_e10(rec: RecordConfig, machine_id: str, reason: str | None) -> str:
    """SEMI E10 state of a stop beginning now: non-scheduled outside planned time, else its reason's."""
    if not is_planned(rec.calendar_of(machine_id), datetime.now(UTC), rec.timezone):
        return "non_scheduled"
    return rec.reasons[reason][1] if reason in rec.reasons else "unscheduled_downtime"


class MachineServer(Server, Module):
    role = "ms"

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.machines: dict[str, _Watch] = {}
        self.pruner = Pruner("ms", "machine history", cfg.record, self.transaction, log)

    def handlers(self) -> dict[str, Handler]:
        return {
            Conv.CHG_STATUS: self.change_status,
            Conv.GET_STATUS: self.get_status,
            Conv.RUN_COMPL: self.run_complete,
            Conv.MAINT_DONE: self.maintenance_done,
            Conv.SCRAP_RPT: self.scrap,
            Conv.MOD_DIED: self.module_died,
            Conv.DOWNTIME_RSN: self.downtime_reason,
        }

    def refusal(self, cls: str, req: Message, code: str, note: str) -> Message | None:
        if cls == Conv.GET_STATUS:
            return message(Msg.STATUS_REPLY, machine_id=req.machine_id, ack_code=code, note=note[:500])
        return None

    # ----------------------------------------------------------------- lifecycle

    async def on_startup(self) -> str:
        """Load every machine (rows for configured machines that lack one) and start watching them."""
        every = {}
        for m in self.cfg.machines:
            n = m.options.get("maintenance_every")
            if isinstance(n, int) and not isinstance(n, bool) and n > 0:
                every[m.id] = n
            elif n is not None:
                self.log.error("machine %s: maintenance_every = %r is not a positive whole number: ignored", m.id, n)
        now = time.monotonic()
        watched = self.transaction(lambda cur: machine_store.load(cur, every))
        self.machines = {w.machine_id: _Watch(w.status, w.liveness, now) for w in watched}
        up = sorted(m for m, w in self.machines.items() if w.status != MachineStatus.SHUTDOWN)
        self.log.info("watching %d machines%s", len(self.machines), f" ({', '.join(up)} up)" if up else "")
        return AckCode.ACK_OK

    # ----------------------------------------------------------------- liveness

    async def on_idle(self) -> None:
        """The WC of a machine that is up fell silent: the machine is Shutdown; tell the cell."""
        if not self.started:
            return
        now = time.monotonic()
        self.pruner.on_idle(now)
        peers = self.bus.peers()
        for mid, w in list(self.machines.items()):
            peer = peers.get(f"wc:{mid}")
            if peer is not None:
                w.last_seen = max(w.last_seen, peer.last_seen)
            silent = now - w.last_seen
            if w.status != MachineStatus.SHUTDOWN and silent > w.liveness:
                note = f"WC wc:{mid} silent for {silent:.1f}s (liveness {w.liveness:g}s): machine Shutdown"
                await self.shut_down(mid, note, "WC_SILENT", "liveness")

    async def module_died(self, conv: Conversation) -> None:
        """MOD_DIED (broadcast by a host's agent): a machine whose ME died has lost its state and its run
        (machine-interface.md, section 7), so it is Shutdown now, not after the liveness window. A WC
        that died is being restarted and resumes its machine, so its run is only in doubt: nothing
        changes unless the agent gave it up (FATAL)."""
        died = self.request(conv)
        kind, _, machine_id = died.module.partition(":")
        if machine_id not in self.machines or kind not in ("me", "wc"):
            return
        if kind == "wc" and died.state != "FATAL":
            self.log.info("wc:%s died (%s); its agent restarts it (%s)", machine_id, died.how, died.state)
            return
        what = "ME" if kind == "me" else "WC, given up by its agent,"
        note = f"{what} {died.module} died ({died.how}, told by {died.host}): machine Shutdown"
        await self.shut_down(machine_id, note, None, "agent_death")

    async def shut_down(self, machine_id: str, note: str, alarm_id: str | None, cause: str) -> None:
        """A machine the cell cannot use any more goes Shutdown at once, broadcast (MSCHED then routes
        around it, lots on it hear of it), with an alarm if one is named."""
        w = self.machines[machine_id]
        self.log.error("%s", note)
        others = set(MachineStatus) - {MachineStatus.SHUTDOWN}
        done = self._change(machine_id, MachineStatus.SHUTDOWN, others, note=note, cause=cause, reason=alarm_id)
        w.status = MachineStatus.SHUTDOWN
        if done is None or not done.changed:  # no such machine, or Shutdown already
            return
        await self.broadcast(
            Conv.UPD_ME_ST,
            message(
                Msg.UPDATE_ME_STATUS,
                machine_id=machine_id,
                status=MachineStatus.SHUTDOWN.value,
                previous=done.previous,
                machine_run_id=done.machine_run_id,
                note=note,
            ),
        )
        if alarm_id is not None:
            self.spawn(self.raise_alarm(alarm_id, note, machine_id))

    def _change(
        self, machine_id: str, status: MachineStatus, allowed: set[MachineStatus], **fields: Any
    ) -> machine_store.Change | None:
        """machine_store.change, with the record setting and the E10 state of a stop beginning now."""
        rec = self.cfg.record
        e10 = stop_e10(rec, machine_id, fields.get("reason")) if status == MachineStatus.SHUTDOWN else None
        return machine_store.change(
            self.transaction,
            machine_id,
            status,
            allowed,
            record=rec.history,
            e10=e10 or "unscheduled_downtime",
            **fields,
        )

    # ----------------------------------------------------------------- conversations

    async def change_status(self, conv: Conversation) -> None:
        """CHG_STATUS: one checked change, broadcast; Notnow (with the status now) if it does not fit."""
        req = self.request(conv)
        try:
            status = MachineStatus(req.status)
            expect = None if req.expect is None else {MachineStatus(s) for s in req.expect}
        except (ValueError, TypeError):
            known = ", ".join(MachineStatus)
            raise Refused(
                AckCode.BAD_MESSAGE, f"status {req.status!r} or expect {req.expect!r} is not a machine status ({known})"
            ) from None
        reachable = {c for c in MachineStatus if status in TRANSITIONS[c]}
        fields = {"recipe_id": req.recipe_id, "run": req.machine_run_id, "note": req.note}
        done = self._change(req.machine_id, status, reachable & expect if expect else reachable, **fields)
        if done is None:
            raise Refused(AckCode.UNKNOWN, f"no machine {req.machine_id!r}")
        previous = done.previous
        if not done.changed:
            if expect and previous not in expect:
                why = f"machine {req.machine_id} is {previous}, not {' or '.join(sorted(expect))}"
            else:
                why = f"machine {req.machine_id} cannot go from {previous} to {status}"
            raise Refused(AckCode.NOTNOW, why, status=previous.value)
        w = self.machines.get(req.machine_id)
        if w is None:  # a machine registered after we started
            live = self.transaction(machine_store.liveness(req.machine_id))
            w = self.machines[req.machine_id] = _Watch(status, live, time.monotonic())
        if previous == MachineStatus.SHUTDOWN or conv.peer == f"wc:{req.machine_id}":
            w.last_seen = time.monotonic()  # the watch starts (again) now
        w.status = status
        self.log.info("%s: %s -> %s%s", req.machine_id, previous, status, f" ({req.note})" if req.note else "")
        await self.answer(conv, Msg.CHANGE_STATUS_ACK, status=status.value, previous=previous.value)
        if status != previous:
            await self.broadcast(
                Conv.UPD_ME_ST,
                message(
                    Msg.UPDATE_ME_STATUS,
                    machine_id=req.machine_id,
                    status=status.value,
                    previous=previous.value,
                    machine_run_id=done.machine_run_id,
                    note=req.note,
                ),
            )

    async def downtime_reason(self, conv: Conversation) -> None:
        """DOWNTIME_RSN: the operator's reason for a downtime event (the open one of a machine, or by
        number), one of the reason tree's; its E10 state follows the reason's category (a stop outside
        planned time stays non-scheduled)."""
        req = self.request(conv)
        rec = self.cfg.record
        if req.reason not in rec.reasons:
            known = "; ".join(f"{c}: {', '.join(rs)}" for c, rs in rec.tree().items())
            raise Refused(AckCode.BAD_MESSAGE, f"{req.reason!r} is not in the reason tree ({known})")
        if (req.event_id is None) == (req.machine_id is None):
            raise Refused(AckCode.BAD_MESSAGE, "name the event_id or the machine_id (one)")
        by = req.by or conv.peer
        e10 = rec.reasons[req.reason][1]
        done = self.transaction(machine_store.downtime_reason(req.reason, by, e10, req.event_id, req.machine_id))
        self.log.info(
            "downtime %d of %s: reason %r (%s) by %s", done.event_id, done.machine_id, req.reason, done.e10_state, by
        )
        await self.answer(conv, Msg.DOWNTIME_REASON_ACK, event_id=done.event_id, e10_state=done.e10_state)
        await self.event(f"{done.machine_id}: downtime {done.event_id} reason {req.reason} ({by})")

    async def get_status(self, conv: Conversation) -> None:
        req = self.request(conv)
        row = self.transaction(machine_store.status(req.machine_id))
        await self.answer(
            conv,
            Msg.STATUS_REPLY,
            AckCode.ACK_OK,
            row.note,
            machine_id=req.machine_id,
            status=row.status,
            recipe_id=row.recipe_id,
            machine_run_id=row.machine_run_id,
        )

    async def run_complete(self, conv: Conversation) -> None:
        """RUN_COMPL (broadcast by a WC): count the run; maintenance due?"""
        done = self.request(conv)
        failed = done.ack_code != AckCode.ACK_OK
        # heard once: kept until the database is back
        count = await self.transaction_when_up(machine_store.count_run(done.machine_id))
        if count is None:
            self.log.warning("Run_Complete for unknown machine %s ignored", done.machine_id)
            return
        self.log.info(
            "%s: run %s %s; %d runs since maintenance",
            done.machine_id,
            done.machine_run_id,
            "failed" if failed else "complete",
            count.runs,
        )
        if count.every is not None and count.runs == count.every:
            text = f"{done.machine_id}: maintenance is due ({count.runs} runs since the last)"
            self.spawn(self.raise_alarm("MAINT_DUE", text, done.machine_id))

    async def scrap(self, conv: Conversation) -> None:
        """SCRAP_RPT: a lot entity's verdict scrapped parts a machine's run made; the machine's scrap count
        grows by them, once per (run, machine, entity). A lot script reports in its own name only."""
        req = self.request(conv)
        if conv.initiator.startswith("lot:") and conv.initiator != f"lot:{req.entity_id}":
            raise Refused(AckCode.NOT_AUTH, f"{conv.initiator} reports for itself only")
        if req.parts <= 0:
            raise Refused(AckCode.BAD_MESSAGE, "parts must be 1 or more")
        scrap = (req.machine_run_id, req.machine_id, req.entity_id, req.parts, req.reason)
        booked = await self.transaction_when_up(lambda cur: machine_store.book_scrap(cur, *scrap), DATABASE_OUTAGE_S)
        if booked:
            self.log.info(
                "%s: %d part(s) of run %d scrapped by entity %d: %s",
                req.machine_id,
                req.parts,
                req.machine_run_id,
                req.entity_id,
                req.reason or "-",
            )
        await self.answer(conv, Msg.ACK, AckCode.ACK_OK, None if booked else "already reported")

    async def maintenance_done(self, conv: Conversation) -> None:
        """MAINT_DONE: the operator maintained a machine; the run count starts again."""
        req = self.request(conv)
        runs = self.transaction(machine_store.maintained(req.machine_id, req.by, self.cfg.record.history))
        self.log.info("%s maintained by %s after %d runs", req.machine_id, req.by or "?", runs)
        await self.answer(conv, Msg.MAINT_DONE_ACK, AckCode.ACK_OK, runs=runs)
