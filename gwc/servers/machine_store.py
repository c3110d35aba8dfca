"""The Machine Server's database side: every read and write of MACHINE_STATUS, and of the machines'
history and downtime it records, that its handlers make (gwc/servers/machine.py parses, keeps the
liveness watch, broadcasts and answers).

A function returns a one-statement `Statement` (run alone, without BEGIN and COMMIT) or takes the
cursor of one transaction. Each returns a dataclass and raises `Refused` with the ack code and the
reason when the request does not fit the tables.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from gwc.db import Statement
from gwc.errors import Refused
from gwc.ipc.codes import AckCode, MachineStatus

T = TypeVar("T")
Step = Callable[[Callable[[Any], T]], T]  # a module's transaction: runs one step, retried on a transient failure

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
UPDATE = (
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


@dataclass(frozen=True)
class Watched:
    """A machine as the liveness watch starts from it."""

    machine_id: str
    status: MachineStatus
    liveness: float


@dataclass(frozen=True)
class Change:
    """A CHG_STATUS's outcome: the status before, the run the row names, and whether it changed (else
    `previous` is the status the machine is in, which did not allow the change)."""

    previous: MachineStatus
    machine_run_id: int | None
    changed: bool


@dataclass(frozen=True)
class Status:
    """A machine's row, as GET_STATUS answers it."""

    status: str
    recipe_id: str | None
    machine_run_id: int | None
    note: str | None


@dataclass(frozen=True)
class RunCount:
    """A machine's runs since maintenance, after a Run_Complete, and its maintenance interval (if any)."""

    runs: int
    every: int | None


@dataclass(frozen=True)
class Reason:
    """A downtime event given its reason: its number, its E10 state now, its machine."""

    event_id: int
    e10_state: str
    machine_id: str


def load(cur: Any, every: dict[str, int]) -> list[Watched]:
    """Every machine, a row made for each configured machine that lacks one, with its maintenance
    interval (cell.toml `maintenance_every`) set."""
    cur.execute(
        "insert into machine_status (machine_id, status) select machine_id, 'Shutdown' "
        "from me_config on conflict do nothing"
    )
    for mid, n in every.items():
        cur.execute("update machine_status set maintenance_every = %s where machine_id = %s", (n, mid))
    rows = cur.execute(
        "select s.machine_id, s.status, c.liveness_s from machine_status s join me_config c using (machine_id)"
    ).fetchall()
    return [Watched(mid, MachineStatus(status), float(live)) for mid, status, live in rows]


def change(
    step: Step[Any], machine_id: str, status: MachineStatus, allowed: set[MachineStatus], **fields: Any
) -> Change | None:
    """The machine goes to `status` if it is in an `allowed` one, its history and downtime recorded
    (`record`) in the same statement; `e10` is the SEMI E10 state of a stop beginning now. None: no
    such machine. Two single statements, each run alone: the second, only after a refusal, reads a
    snapshot of its own, as it did in one read-committed step."""
    params = {"recipe_id": None, "run": None, "note": None, "cause": None, "reason": None} | fields
    if (
        status == MachineStatus.SHUTDOWN
        and params["cause"] is None
        and str(params["note"] or "").startswith("operator")
    ):
        params["cause"] = "operator_stop"  # the WC's ME_SHUT (gwc/wc/wc.py)
    params |= {"status": status.value, "machine_id": machine_id, "from": [s.value for s in allowed]}
    row = step(Statement(UPDATE, params))
    if row is not None:
        return Change(MachineStatus(row[0]), row[1], True)
    now = step(Statement("select status from machine_status where machine_id = %s", (machine_id,)))
    return None if now is None else Change(MachineStatus(now[0]), None, False)


def liveness(machine_id: str) -> Statement:
    """A machine's liveness window (me_config.liveness_s), 3 s if it has no row."""
    return Statement(
        "select liveness_s from me_config where machine_id = %s",
        (machine_id,),
        into=lambda row: float(row[0]) if row else 3.0,
    )


def status(machine_id: str) -> Statement:
    """A machine's status row; Refused UNKNOWN if there is no such machine."""

    def into(row: tuple[Any, ...] | None) -> Status:
        if row is None:
            raise Refused(AckCode.UNKNOWN, f"no machine {machine_id!r}")
        return Status(*row)

    return Statement(
        "select status, recipe_id, machine_run_id, note from machine_status where machine_id = %s",
        (machine_id,),
        into=into,
    )


def count_run(machine_id: str) -> Statement:
    """One more run since maintenance (scrap is the lots' verdict: book_scrap); None: no such machine."""
    return Statement(
        "update machine_status set runs_since_maintenance = runs_since_maintenance + 1 where machine_id = %s "
        "returning runs_since_maintenance, maintenance_every",
        (machine_id,),
        into=lambda row: None if row is None else RunCount(row[0], row[1]),
    )


def book_scrap(cur: Any, machine_run_id: int, machine_id: str, entity_id: int, parts: int, reason: str | None) -> bool:
    """A lot entity's scrapped parts of a machine's run, counted once per (run, machine, entity): True
    if booked now, False if reported before. Refused UNKNOWN for a run the machine never made."""
    if not cur.execute(
        "select 1 from machine_run_outcome where machine_run_id = %s and machine_id = %s",
        (machine_run_id, machine_id),
    ).fetchone():
        raise Refused(AckCode.UNKNOWN, f"no run {machine_run_id} on {machine_id}")
    if not cur.execute(
        "insert into scrap_reports (machine_run_id, machine_id, entity_id, parts, reason) "
        "values (%s, %s, %s, %s, %s) on conflict do nothing returning 1",
        (machine_run_id, machine_id, entity_id, parts, reason),
    ).fetchone():
        return False
    cur.execute("update machine_status set scrap_count = scrap_count + %s where machine_id = %s", (parts, machine_id))
    return True


def maintained(machine_id: str, by: str | None, record: bool) -> Statement:
    """The machine was maintained: its run count starts again (recorded in its history when `record`);
    the runs it had made since the last. Refused UNKNOWN if there is no such machine."""

    def into(row: tuple[Any, ...] | None) -> int:
        if row is None:
            raise Refused(AckCode.UNKNOWN, f"no machine {machine_id!r}")
        return int(row[0])

    return Statement(
        "with m as (update machine_status m set runs_since_maintenance = 0, updated_at = now() "
        "from machine_status old where m.machine_id = %(m)s and old.machine_id = m.machine_id "
        "returning old.runs_since_maintenance, m.status), "
        "h as (insert into machine_state_history (machine_id, status, previous, cause, note) "
        "select %(m)s, status, status, 'maintenance', %(note)s from m where %(record)s) "
        "select runs_since_maintenance from m",
        {"m": machine_id, "note": f"maintained by {by or '?'}", "record": record},
        into=into,
    )


def downtime_reason(reason: str, by: str | None, e10: str, event_id: int | None, machine_id: str | None) -> Statement:
    """The operator's reason for a downtime event (by number, else the machine's open one); its E10
    state becomes `e10` unless it is non-scheduled. Refused UNKNOWN if there is no such event."""

    def into(row: tuple[Any, ...] | None) -> Reason:
        if row is None:
            what = f"event {event_id}" if event_id is not None else f"open downtime of {machine_id}"
            raise Refused(AckCode.UNKNOWN, f"no {what}")
        return Reason(*row)

    return Statement(
        "update downtime_events set reason = %(reason)s, reason_by = %(by)s, reason_at = clock_timestamp(), "
        "e10_state = case when e10_state = 'non_scheduled' then e10_state else %(e10)s end "
        "where case when %(event)s::bigint is not null then event_id = %(event)s "
        "else machine_id = %(machine)s and ended_at is null end returning event_id, e10_state, machine_id",
        {"reason": reason, "by": by, "e10": e10, "event": event_id, "machine": machine_id},
        into=into,
    )
