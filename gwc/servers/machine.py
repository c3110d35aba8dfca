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

from gwc.config import Config
from gwc.db import Statement
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S, Handler, Module
from gwc.record.calendar import is_planned
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

# The production record (docs/record.md), in the same statement as the change it records: a row of
# machine_state_history for a status that changed, with its cause (given, or told by the transition);
# a downtime event opened when the machine goes Shutdown, closed when it leaves it. %(record)s false
# (cell.toml [record] history = false) writes none of it.
RECORD = """,
hist as (
insert into machine_state_history (machine_id, status, previous, cause, recipe_id, recipe_version, recipe_checksum,
                                   machine_run_id, entity_id, note)
select %(machine_id)s, u.status, u.previous,
       coalesce(%(cause)s, case when u.status = 'Setup' then 'setup'
                                when u.status = 'Running' then 'run'
                                when u.status in ('Setup_Shut', 'Run_Shut') then 'operator_stop'
                                when u.status = 'Idle' and u.previous in ('Running', 'Run_Shut') then 'run_end'
                                when u.status = 'Idle' and u.previous in ('Setup', 'Setup_Shut') then 'setup_end'
                                when u.status = 'Idle' then 'start'
                                when u.previous in ('Setup_Shut', 'Run_Shut') then 'operator_stop'
                                else 'alarm' end),
       case when u.status in ('Setup', 'Running') then u.recipe_id end, v.version, v.checksum,
       case when u.status in ('Setup', 'Running', 'Setup_Shut', 'Run_Shut') then u.machine_run_id end,
       case when u.status in ('Setup', 'Running') then
           (select r.entity_id from reserved_machines r
            where r.machine_id = %(machine_id)s and r.machine_run_id = u.machine_run_id) end,
       %(note)s
from upd u left join recipe_versions v on u.status in ('Setup', 'Running') and v.recipe_id = u.recipe_id and v.approved
where %(record)s and u.status <> u.previous
),
opened as (
insert into downtime_events (machine_id, cause, reason, e10_state, note)
select %(machine_id)s, coalesce(%(cause)s, case when u.previous in ('Setup_Shut', 'Run_Shut') then 'operator_stop'
                                                else 'alarm' end),
       coalesce(%(reason)s, (select a.alarm_id from alarms a where a.machine_id = %(machine_id)s
                             and a.cleared_at is null and a.raised_at > now() - interval '30 seconds'
                             and coalesce(%(cause)s, 'alarm') = 'alarm' order by a.alarm_no desc limit 1)),
       %(e10)s, %(note)s
from upd u where %(record)s and u.status = 'Shutdown' and u.previous <> 'Shutdown'
on conflict do nothing
),
closed as (
update downtime_events d set ended_at = clock_timestamp() from upd u
where %(record)s and d.machine_id = %(machine_id)s and d.ended_at is null and u.status <> 'Shutdown'
)"""

# One checked change, one statement: the row is locked and changed only if its status is one of %(from)s;
# no row back: the status forbids it (or there is no such machine), which a second read tells.
_UPDATE = (
    """
with old as (select status from machine_status where machine_id = %(machine_id)s for update),
upd as (
update machine_status s set
    status = %(status)s,
    recipe_id = coalesce(%(recipe_id)s, s.recipe_id),
    machine_run_id = coalesce(%(run)s, s.machine_run_id),
    start_time = case when %(status)s in ('Running', 'Run_Shut') and s.status not in ('Running', 'Run_Shut')
                          then now()
                      when %(status)s = 'Setup' and s.status <> 'Setup' then null
                      else s.start_time end,
    end_time = case when %(status)s in ('Idle', 'Shutdown') and s.status in ('Running', 'Run_Shut') then now()
                    when %(status)s in ('Setup', 'Running', 'Run_Shut') and s.status not in ('Running', 'Run_Shut')
                        then null
                    else s.end_time end,
    note = %(note)s,
    updated_at = now()
from old
where s.machine_id = %(machine_id)s and old.status = any(%(from)s)
returning old.status as previous, s.status, s.machine_run_id, s.recipe_id
)"""
    + RECORD
    + """
select previous, machine_run_id from upd
"""
)


@dataclass
class _Watch:
    """What the liveness watch knows of one machine."""

    status: MachineStatus
    liveness: float
    last_seen: float  # monotonic time its WC was last heard (or the watch began)


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

        def load(cur: Any) -> list[tuple[str, str, float]]:
            cur.execute(
                "insert into machine_status (machine_id, status) select machine_id, 'Shutdown' "
                "from me_config on conflict do nothing"
            )
            for mid, n in every.items():
                cur.execute("update machine_status set maintenance_every = %s where machine_id = %s", (n, mid))
            return cur.execute(
                "select s.machine_id, s.status, c.liveness_s from machine_status s join me_config c using (machine_id)"
            ).fetchall()

        now = time.monotonic()
        self.machines = {
            mid: _Watch(MachineStatus(status), float(live), now) for mid, status, live in self.transaction(load)
        }
        up = sorted(m for m, w in self.machines.items() if w.status != MachineStatus.SHUTDOWN)
        self.log.info("watching %d machines%s", len(self.machines), f" ({', '.join(up)} up)" if up else "")
        return AckCode.ACK_OK

    # ----------------------------------------------------------------- liveness

    async def on_idle(self) -> None:
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
                await self.machine_silent(mid, silent)

    async def machine_silent(self, machine_id: str, silent: float) -> None:
        """The WC of a machine that is up fell silent: the machine is Shutdown; tell the cell."""
        w = self.machines[machine_id]
        note = f"WC wc:{machine_id} silent for {silent:.1f}s (liveness {w.liveness:g}s): machine Shutdown"
        await self.shut_down(machine_id, note, "WC_SILENT", "liveness")

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

        changed = self._change(
            machine_id,
            MachineStatus.SHUTDOWN,
            set(MachineStatus) - {MachineStatus.SHUTDOWN},
            note=note,
            cause=cause,
            reason=alarm_id,
        )
        w.status = MachineStatus.SHUTDOWN
        if changed is None or not changed[2]:  # no such machine, or Shutdown already
            return
        previous, run, _ = changed
        await self.broadcast(
            Conv.UPD_ME_ST,
            message(
                Msg.UPDATE_ME_STATUS,
                machine_id=machine_id,
                status=MachineStatus.SHUTDOWN.value,
                previous=previous,
                machine_run_id=run,
                note=note,
            ),
        )
        if alarm_id is not None:
            self.spawn(self._alarm(alarm_id, note, machine_id))

    async def _alarm(self, alarm_id: str, text: str, machine_id: str) -> None:
        await self.raise_alarm(alarm_id, text, machine_id)

    def _change(
        self, machine_id: str, status: MachineStatus, allowed: set[MachineStatus], **fields: Any
    ) -> tuple[MachineStatus, int | None, bool] | None:
        """(previous status, machine_run_id, True) if the machine was in an `allowed` status and is now
        `status`; else (its status, None, False), or None (no such machine). Two single statements, each
        run alone: the second, only after a refusal, reads a snapshot of its own, as it did in one
        read-committed step."""
        params = {"recipe_id": None, "run": None, "note": None, "cause": None, "reason": None} | fields
        if (
            status == MachineStatus.SHUTDOWN
            and params["cause"] is None
            and str(params["note"] or "").startswith("operator")
        ):
            params["cause"] = "operator_stop"  # the WC's ME_SHUT (gwc/wc/wc.py)
        params |= {
            "status": status.value,
            "machine_id": machine_id,
            "from": [s.value for s in allowed],
            "record": self.cfg.record.history,
            "e10": self._e10(machine_id, params["reason"])
            if status == MachineStatus.SHUTDOWN
            else "unscheduled_downtime",
        }
        row = self.transaction(Statement(_UPDATE, params))
        if row is not None:
            return MachineStatus(row[0]), row[1], True
        now = self.transaction(Statement("select status from machine_status where machine_id = %s", (machine_id,)))
        return None if now is None else (MachineStatus(now[0]), None, False)

    # ----------------------------------------------------------------- conversations

    async def change_status(self, conv: Conversation) -> None:
        """CHG_STATUS: one checked change, broadcast; Notnow (with the status now) if it does not fit."""
        req = self.request(conv)
        ack = Msg.CHANGE_STATUS_ACK
        try:
            status = MachineStatus(req.status)
            expect = None if req.expect is None else {MachineStatus(s) for s in req.expect}
        except (ValueError, TypeError):
            return await self.answer(
                conv,
                ack,
                AckCode.BAD_MESSAGE,
                f"status {req.status!r} or expect {req.expect!r} is not a machine status ({', '.join(MachineStatus)})",
            )

        reachable = {c for c in MachineStatus if status in TRANSITIONS[c]}
        fields = {"recipe_id": req.recipe_id, "run": req.machine_run_id, "note": req.note}
        result = self._change(req.machine_id, status, reachable & expect if expect else reachable, **fields)
        if result is None:
            return await self.answer(conv, ack, AckCode.UNKNOWN, f"no machine {req.machine_id!r}")
        previous, run, changed = result
        if not changed:
            if expect and previous not in expect:
                why = f"machine {req.machine_id} is {previous}, not {' or '.join(sorted(expect))}"
            else:
                why = f"machine {req.machine_id} cannot go from {previous} to {status}"
            return await self.answer(conv, ack, AckCode.NOTNOW, why, status=previous.value)
        w = self.machines.get(req.machine_id)
        if w is None:  # a machine registered after we started
            w = self.machines[req.machine_id] = _Watch(status, self._liveness(req.machine_id), time.monotonic())
        if previous == MachineStatus.SHUTDOWN or conv.peer == f"wc:{req.machine_id}":
            w.last_seen = time.monotonic()  # the watch starts (again) now
        w.status = status
        self.log.info("%s: %s -> %s%s", req.machine_id, previous, status, f" ({req.note})" if req.note else "")
        await self.answer(conv, ack, AckCode.ACK_OK, status=status.value, previous=previous.value)
        if status != previous:
            await self.broadcast(
                Conv.UPD_ME_ST,
                message(
                    Msg.UPDATE_ME_STATUS,
                    machine_id=req.machine_id,
                    status=status.value,
                    previous=previous.value,
                    machine_run_id=run,
                    note=req.note,
                ),
            )

    def _e10(self, machine_id: str, reason: str | None) -> str:
        """SEMI E10 state of a stop beginning now: non-scheduled outside planned time, else its reason's."""
        rec = self.cfg.record
        if not is_planned(rec.calendar_of(machine_id), datetime.now(UTC), rec.timezone):
            return "non_scheduled"
        return rec.reasons[reason][1] if reason in rec.reasons else "unscheduled_downtime"

    async def downtime_reason(self, conv: Conversation) -> None:
        """DOWNTIME_RSN: the operator's reason for a downtime event (the open one of a machine, or by
        number), one of the reason tree's; its E10 state follows the reason's category (a stop outside
        planned time stays non-scheduled)."""
        req = self.request(conv)
        ack = Msg.DOWNTIME_REASON_ACK
        rec = self.cfg.record
        if req.reason not in rec.reasons:
            known = "; ".join(f"{c}: {', '.join(rs)}" for c, rs in rec.tree().items())
            return await self.answer(
                conv, ack, AckCode.BAD_MESSAGE, f"{req.reason!r} is not in the reason tree ({known})"
            )
        if (req.event_id is None) == (req.machine_id is None):
            return await self.answer(conv, ack, AckCode.BAD_MESSAGE, "name the event_id or the machine_id (one)")
        row = self.transaction(
            Statement(
                "update downtime_events set reason = %(reason)s, reason_by = %(by)s, reason_at = clock_timestamp(), "
                "e10_state = case when e10_state = 'non_scheduled' then e10_state else %(e10)s end "
                "where case when %(event)s::bigint is not null then event_id = %(event)s "
                "else machine_id = %(machine)s and ended_at is null end returning event_id, e10_state, machine_id",
                {
                    "reason": req.reason,
                    "by": req.by or conv.peer,
                    "e10": rec.reasons[req.reason][1],
                    "event": req.event_id,
                    "machine": req.machine_id,
                },
            )
        )
        if row is None:
            what = f"event {req.event_id}" if req.event_id is not None else f"open downtime of {req.machine_id}"
            return await self.answer(conv, ack, AckCode.UNKNOWN, f"no {what}")
        by = req.by or conv.peer
        self.log.info("downtime %d of %s: reason %r (%s) by %s", row[0], row[2], req.reason, row[1], by)
        await self.answer(conv, ack, AckCode.ACK_OK, event_id=row[0], e10_state=row[1])
        await self.event(f"{row[2]}: downtime {row[0]} reason {req.reason} ({req.by or conv.peer})")

    def _liveness(self, machine_id: str) -> float:
        row = self.transaction(Statement("select liveness_s from me_config where machine_id = %s", (machine_id,)))
        return float(row[0]) if row else 3.0

    async def get_status(self, conv: Conversation) -> None:
        req = self.request(conv)

        row = self.transaction(
            Statement(
                "select status, recipe_id, machine_run_id, note from machine_status where machine_id = %s",
                (req.machine_id,),
            )
        )
        if row is None:
            return await self.answer(
                conv, Msg.STATUS_REPLY, AckCode.UNKNOWN, f"no machine {req.machine_id!r}", machine_id=req.machine_id
            )
        await self.answer(
            conv,
            Msg.STATUS_REPLY,
            AckCode.ACK_OK,
            row[3],
            machine_id=req.machine_id,
            status=row[0],
            recipe_id=row[1],
            machine_run_id=row[2],
        )

    async def run_complete(self, conv: Conversation) -> None:
        """RUN_COMPL (broadcast by a WC): count the run; maintenance due?"""
        done = self.request(conv)
        failed = done.ack_code != AckCode.ACK_OK

        count = Statement(  # (scrap is the lots' verdict: SCRAP_RPT, below)
            "update machine_status set runs_since_maintenance = runs_since_maintenance + 1 where machine_id = %s "
            "returning runs_since_maintenance, maintenance_every",
            (done.machine_id,),
        )
        row = await self.transaction_when_up(count)  # heard once: kept until the database is back
        if row is None:
            self.log.warning("Run_Complete for unknown machine %s ignored", done.machine_id)
            return
        runs, every = row
        self.log.info(
            "%s: run %s %s; %d runs since maintenance",
            done.machine_id,
            done.machine_run_id,
            "failed" if failed else "complete",
            runs,
        )
        if every is not None and runs == every:
            self.spawn(
                self._alarm(
                    "MAINT_DUE", f"{done.machine_id}: maintenance is due ({runs} runs since the last)", done.machine_id
                )
            )

    async def scrap(self, conv: Conversation) -> None:
        """SCRAP_RPT: a lot entity's verdict scrapped parts a machine's run made; the machine's scrap count
        grows by them, once per (run, machine, entity). A lot script reports in its own name only."""
        req = self.request(conv)
        if conv.initiator.startswith("lot:") and conv.initiator != f"lot:{req.entity_id}":
            return await self.answer(conv, Msg.ACK, AckCode.NOT_AUTH, f"{conv.initiator} reports for itself only")
        if req.parts <= 0:
            return await self.answer(conv, Msg.ACK, AckCode.BAD_MESSAGE, "parts must be 1 or more")

        def book(cur: Any) -> str | None:
            if not cur.execute(
                "select 1 from machine_run_outcome where machine_run_id = %s and machine_id = %s",
                (req.machine_run_id, req.machine_id),
            ).fetchone():
                return f"no run {req.machine_run_id} on {req.machine_id}"
            if cur.execute(
                "insert into scrap_reports (machine_run_id, machine_id, entity_id, parts, reason) "
                "values (%s, %s, %s, %s, %s) on conflict do nothing returning 1",
                (req.machine_run_id, req.machine_id, req.entity_id, req.parts, req.reason),
            ).fetchone():
                cur.execute(
                    "update machine_status set scrap_count = scrap_count + %s where machine_id = %s",
                    (req.parts, req.machine_id),
                )
                return None
            return "already reported"

        why = await self.transaction_when_up(book, within=DATABASE_OUTAGE_S)
        if why is not None and why != "already reported":
            return await self.answer(conv, Msg.ACK, AckCode.UNKNOWN, why)
        if why is None:
            self.log.info(
                "%s: %d part(s) of run %d scrapped by entity %d: %s",
                req.machine_id,
                req.parts,
                req.machine_run_id,
                req.entity_id,
                req.reason or "-",
            )
        await self.answer(conv, Msg.ACK, AckCode.ACK_OK, why)

    async def maintenance_done(self, conv: Conversation) -> None:
        """MAINT_DONE: the operator maintained a machine; the run count starts again."""
        req = self.request(conv)

        row = self.transaction(
            Statement(
                "with m as (update machine_status m set runs_since_maintenance = 0, updated_at = now() "
                "from machine_status old where m.machine_id = %(m)s and old.machine_id = m.machine_id "
                "returning old.runs_since_maintenance, m.status), "
                "h as (insert into machine_state_history (machine_id, status, previous, cause, note) "
                "select %(m)s, status, status, 'maintenance', %(note)s from m where %(record)s) "
                "select runs_since_maintenance from m",
                {"m": req.machine_id, "note": f"maintained by {req.by or '?'}", "record": self.cfg.record.history},
            )
        )
        if row is None:
            return await self.answer(conv, Msg.MAINT_DONE_ACK, AckCode.UNKNOWN, f"no machine {req.machine_id!r}")
        self.log.info("%s maintained by %s after %d runs", req.machine_id, req.by or "?", row[0])
        await self.answer(conv, Msg.MAINT_DONE_ACK, AckCode.ACK_OK, runs=row[0])
