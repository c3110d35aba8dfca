"""The database side of MSCHED, in one place: every read and write the scheduler makes.

A `Step` is one transaction: the changes of one or more conversations (a request queued, a machine
freed, accept types changed, a machine shut down ...) followed by ONE scheduling pass over the
machines those changes may have made usable. Committing both together is what makes a crash
harmless: either the machine was freed and whoever could use it was bound, or neither happened.

What the scheduler decided, and has not yet heard acknowledged, is stored too (REQUEST_OUTCOMES):
a request leaves REQUEST_MACHINES in the same transaction that writes its outcome, so after a
kill -9 the new MSCHED resends exactly the answers that were not acknowledged, and never decides
a request twice (docs/scheduling.md, "Restart without loss").

The scheduling pass keeps one invariant: after every step, no queued request can be bound. So a
step only has to look at requests that touch a machine the step may have made usable (its
"triggers"): a request queued, a machine freed, started or given new accept types. That keeps a
pass over 10,000 queued requests to a few index lookups. A machine freed or given new accept types
with no request queued for it triggers nothing (the statement that frees it says so), so the step
of a lot's unreserve or of a WC's "accepts all" makes no pass when nobody waits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc.db import Statement
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.msched.policy import Candidate, Policy

# A machine in one of these states is up: it can be bound (when it is free and accepts the op type).
UP = (MachineStatus.IDLE.value, MachineStatus.SETUP.value, MachineStatus.RUNNING.value)
_OUTCOME_COLS = "request_key, entity_id, ack_code, machines, machine_run_id, note, reply_to, reply_conv"
# Candidates fetched per freed machine and round; the pass repeats while a round binds something.
PER_MACHINE = 4


def first(row: tuple[Any, ...] | None) -> Any:
    """The first column of the row a statement always returns (an insert's RETURNING, a function's select)."""
    assert row is not None, "the statement returned no row"
    return row[0]


@dataclass(frozen=True)
class Outcome:
    """How a request ended: the Machine_Req_Comp its entity is owed."""

    request_key: int
    entity_id: int
    ack_code: str  # ACK_OK (bound), NO_MACHINE, REQ_CANCEL
    machines: tuple[str, ...]  # ACK_OK: the machines reserved; otherwise those it asked for
    machine_run_id: int | None
    note: str | None
    reply_to: str | None  # the bus module to tell
    reply_conv: str | None  # the MACH_REQ conversation to tell it in

    @classmethod
    def of(cls, row: Sequence[Any]) -> Outcome:
        key, entity, code, machines, run_id, note, reply_to, reply_conv = row
        return cls(int(key), int(entity), code, tuple(machines), run_id, note, reply_to, reply_conv)


# Chg_Accept_Type in one statement (it was four or five round trips, twice a lot): the machine known, the
# op types wanted (all of the machine's recipes', or those named, each known), and only then the
# accept types made so; what was added triggers a scheduling pass.
_ACCEPT = """
with machine as (select 1 from me_config where machine_id = %(m)s),
wanted as (select r.op_type from op_machine_recipe r where %(all)s and r.machine_id = %(m)s
           union select t.op_type from op_types t where not %(all)s and t.op_type = any(%(types)s)),
unknown as (select u from unnest(%(types)s::text[]) u where u not in (select op_type from wanted)),
ok as (select 1 from machine where not exists (select 1 from unknown)),
gone as (delete from accept_types a where a.machine_id = %(m)s and exists (select 1 from ok)
         and a.op_type not in (select op_type from wanted)),
added as (insert into accept_types (machine_id, op_type) select %(m)s, op_type from wanted
          where exists (select 1 from ok) on conflict do nothing returning 1)
select exists (select 1 from machine), array(select distinct u from unknown order by u),
       array(select op_type from wanted order by op_type), (select count(*) from added),
       exists (select 1 from request_machines q where q.machine_id = %(m)s)
"""


@dataclass(frozen=True)
class Queued:
    """The answer to a Machine_Request: ACK_OK with its request_key, or why not."""

    ack_code: str
    request_key: int | None = None
    note: str | None = None


class Step:
    """One transaction of MSCHED: changes first, then `schedule()` binds what they made possible."""

    def __init__(self, cur: psycopg.Cursor[Any], policy: Policy, per_machine: int = PER_MACHINE) -> None:
        self.cur = cur
        self.policy = policy
        self.per_machine = per_machine
        self.triggers: set[str] = set()  # machines that may have become usable in this step
        self.full = False  # look at every free machine (startup, the periodic sweep)
        self.outcomes: list[Outcome] = []  # Machine_Req_Comp to send once this step commits

    # ------------------------------------------------------------------ conversations

    def queue_request(
        self,
        entity_id: int,
        op_type: str,
        machines: Sequence[str],
        priority: int | None,
        reply_to: str | None,
        reply_conv: str | None,
        alt_group: str | None = None,
    ) -> Queued:
        """Machine_Request: check it and put it in REQUEST_MACHINES (6.2.4.3).

        A request whose alternative group (entity, alt_group) was bound already is refused
        REQ_CANCEL: its need is met, and queued it would wait forever or bind the entity twice.
        """
        cur = self.cur
        # One round trip for what must be checked: a repeat (a step retried after a lost commit gets
        # the same answer), the entity, its group, the op type, the machines' status; one to insert.
        row = cur.execute(
            "select coalesce((select request_key from request_machines where reply_conv = %(conv)s limit 1), "
            "                (select request_key from request_outcomes where reply_conv = %(conv)s limit 1)), "
            "       (select array[exists (select 1 from live_entities v where v.entity_id = e.entity_id)::text, "
            "                     s.state, l.priority::text] from lot_entities e "
            "        join lots l on l.lot_id = e.lot_id left join lot_status s on s.entity_id = e.entity_id "
            "        where e.entity_id = %(entity)s), "
            "       (select request_key from satisfied_alt_groups where entity_id = %(entity)s "
            "        and alt_group = %(group)s), "
            "       exists (select 1 from op_types where op_type = %(op)s), "
            "       (select array_agg(array[c.machine_id, coalesce(s.status, '')]) from me_config c "
            "        left join machine_status s on s.machine_id = c.machine_id where c.machine_id = any(%(machines)s))",
            {"conv": reply_conv, "entity": entity_id, "group": alt_group, "op": op_type, "machines": list(machines)},
        ).fetchone()
        assert row is not None
        repeat, ent, satisfied_by, op_known, statuses = row
        if repeat is not None:
            return Queued(AckCode.ACK_OK, int(repeat), "already queued")
        if ent is None:
            return Queued(AckCode.UNKNOWN, note=f"entity {entity_id} is not known to the Lot Server")
        alive, state, lot_priority = ent
        if alive != "true":
            return Queued(
                AckCode.NOTNOW,
                note=f"entity {entity_id} is {state or 'without a lot status'}: it cannot ask for machines",
            )
        if satisfied_by is not None:
            return Queued(AckCode.REQ_CANCEL, note=f"alternative {satisfied_by} already satisfied")
        if not op_known:
            return Queued(AckCode.UNKNOWN, note=f"op type {op_type!r} is not known")
        status = {m: st for m, st in statuses or ()}
        for m in machines:
            if m not in status:
                return Queued(AckCode.NO_MACHINE, note=f"machine {m} does not exist (ME_CONFIG)")
            if status[m] not in UP:
                return Queued(AckCode.NO_MACHINE, note=f"machine {m} is {status[m] or 'without a status'}")
        key = int(
            first(
                cur.execute(
                    "with k (key, requested_at, priority) as "
                    "    (select get_new_max_value('MACH_R_KEY'), clock_timestamp(), %s::int) "
                    "insert into request_machines (request_key, entity_id, machine_id, op_type, priority, reply_to, "
                    "                              reply_conv, requested_at, slots, alt_group, rank) "
                    f"select k.key, %s, m, %s, k.priority, %s, %s, k.requested_at, %s, %s, {self.policy.rank_sql()} "
                    "from k, unnest(%s::text[]) with ordinality as u (m, i) order by i "
                    "returning request_key",
                    (
                        int(lot_priority) if priority is None else priority,
                        entity_id,
                        op_type,
                        reply_to,
                        reply_conv,
                        [f"{m}:{op_type}" for m in machines],
                        alt_group,
                        list(machines),
                    ),
                ).fetchone()
            )
        )
        self.triggers.update(machines)
        return Queued(AckCode.ACK_OK, key)

    def cancel(self, request_key: int | None, entity_id: int | None, by: str | None = None) -> int:
        """Cancel_Request: end one request (or all of an entity's) with REQ_CANCEL; how many ended."""
        where, params = [], []
        if request_key is not None:
            where.append("request_key = %s")
            params.append(request_key)
        if entity_id is not None:
            where.append("entity_id = %s")
            params.append(entity_id)
        if not where:
            return 0
        cond = " and ".join(where)
        note = f"cancelled by {by}" if by else "cancelled"
        ended = self._end_queued(cond, params, AckCode.REQ_CANCEL, note)
        ended += self._release_held(f"{cond}", params, AckCode.REQ_CANCEL, note)
        self._settle({o.entity_id for o in ended})
        return len(ended)

    def unreserve(self, entity_id: int, machine_id: str | None) -> list[str]:
        """Unreserve_Me: free one machine of an entity, or all of them; the machines freed."""
        return self.unreserve_all([(entity_id, machine_id)])[0]

    def unreserve_all(self, frees: Sequence[tuple[int, str | None]]) -> list[list[str]]:
        """Many Unreserve_Me in one statement (a step's worth under load); the machines each freed."""
        # A machine two frees name (its own, then all of the entity's) goes to the first, as one by one.
        rows = self.cur.execute(
            "with f (i, entity_id, machine_id) as (select * from unnest(%s::int[], %s::bigint[], %s::text[])), "
            "d as (select distinct on (r.machine_id) r.machine_id, f.i from reserved_machines r join f "
            "      on r.entity_id = f.entity_id and (f.machine_id is null or r.machine_id = f.machine_id) "
            "      order by r.machine_id, f.i) "
            "delete from reserved_machines r using d where r.machine_id = d.machine_id returning d.i, r.machine_id, "
            "exists (select 1 from request_machines q where q.machine_id = r.machine_id)",
            (list(range(len(frees))), [e for e, _ in frees], [m for _, m in frees]),
        ).fetchall()
        freed: list[list[str]] = [[] for _ in frees]
        for i, m, _ in rows:
            freed[i].append(m)
        self.triggers.update(m for _, m, waited_for in rows if waited_for)
        return freed

    def set_accept_types(self, machine_id: str, op_types: Sequence[str]) -> tuple[str, str]:
        """Chg_Accept_Type: what the machine accepts from now on (['*'] = all it has recipes for)."""
        every = list(op_types) == ["*"]
        row = self.cur.execute(_ACCEPT, {"m": machine_id, "all": every, "types": [] if every else list(op_types)})
        known, unknown, wanted, added, waited_for = row.fetchone() or (False, [], [], 0, False)
        if not known:
            return AckCode.UNKNOWN, f"machine {machine_id} does not exist (ME_CONFIG)"
        if unknown:
            return AckCode.UNKNOWN, f"op type(s) {', '.join(unknown)} not known"
        if added and waited_for:
            self.triggers.add(machine_id)
        return AckCode.ACK_OK, f"{machine_id} accepts {', '.join(wanted) or 'nothing'}"

    def machine_up(self, machine_id: str) -> None:
        """Update_ME_Status to an up status: the machine may serve someone now."""
        self.triggers.add(machine_id)

    def machines_down(self) -> int:
        """End every queued request that waits for a shut-down machine (6.2.4.5); how many left the queue.

        A request that lost a machine leaves the queue at once. Its entity is told NO_MACHINE only
        when it has no live alternative left; otherwise the outcome is held, untold, until the
        entity's fate is known (an alternative bound -> REQ_CANCEL, the last one lost -> NO_MACHINE).
        """
        rows = self.cur.execute(
            "select q.request_key, q.machine_id from request_machines q join machine_status s on s.machine_id = "
            "q.machine_id where s.status = %s",
            (MachineStatus.SHUTDOWN.value,),
        ).fetchall()
        if not rows:
            return 0
        keys = sorted({r[0] for r in rows})
        down = sorted({r[1] for r in rows})
        note = f"machine {', '.join(down)} shut down"
        held = self._end_queued("request_key = any(%s)", [keys], AckCode.NO_MACHINE, note, held=True)
        self._settle({o.entity_id for o in held})
        return len(keys)

    def finish(self, request_keys: Sequence[int]) -> None:
        """The entities acknowledged (or never will): forget these outcomes."""
        self.cur.execute("delete from request_outcomes where request_key = any(%s) and not held", (list(request_keys),))

    def shutdown_all(self, note: str) -> int:
        """MSCHED shuts down: every waiting request ends NO_MACHINE (6.2.4.2). How many."""
        ended = self._end_queued("true", [], AckCode.NO_MACHINE, note)
        ended += self._release_held("true", [], AckCode.NO_MACHINE, None)
        return len(ended)

    def startup(self, clean: bool) -> list[Outcome]:
        """At start: wipe (--clean, the thesis's way) or carry on; return answers owed from before."""
        cur = self.cur
        if clean:
            for table in ("request_outcomes", "request_machines", "reserved_machines", "satisfied_alt_groups"):
                cur.execute(f"delete from {table}")
            owed: list[Outcome] = []
        else:
            owed = [
                Outcome.of(r)
                for r in cur.execute(
                    f"select {_OUTCOME_COLS} from request_outcomes where not held order by decided_at, request_key"
                )
            ]
            # The policy, or its ageing, may have changed since the requests were queued.
            rank = self.policy.rank_sql()
            cur.execute(f"update request_machines set rank = {rank} where rank is distinct from {rank}")
        self.end_finished()  # entities that finished while MSCHED was away
        self.machines_down()
        self.analyze()
        self.full = True
        return owed

    def sweep(self) -> None:
        """The periodic safety net: a status change whose broadcast never came, an orphan request."""
        self.end_finished()
        self.machines_down()
        self.analyze()
        self.full = True

    def analyze(self) -> bool:
        """Refresh the planner's statistics of the queue if much of it changed (sql msched_analyze()).

        The pass's per-machine walk is the plan PostgreSQL picks only when it knows how long the
        queue is; whether they were refreshed.
        """
        return bool(first(self.cur.execute("select msched_analyze()").fetchone()))

    def end_finished(self) -> int:
        """Entities that finished (or were destroyed) will never take a machine: end their queued
        requests REQ_CANCEL ("entity finished"), free the machines they still hold, and forget the
        alternative groups they were served.

        The pass never binds such a request; this takes it out of the queue, so that an orphan cannot
        linger (e.g. an alternative sent without alt_group that arrived just after its sibling was
        bound). A finished entity holding machines failed while it could not unreserve them (its
        UNRESERVE went unanswered, the database away) after its failure was recorded: the lot
        library unreserves before it completes. How many requests ended.
        """
        ended = self._end_queued(
            "not exists (select 1 from live_entities v where v.entity_id = request_machines.entity_id)",
            [],
            AckCode.REQ_CANCEL,
            "entity finished",
        )
        self._settle({o.entity_id for o in ended})
        freed = self.cur.execute(
            "delete from reserved_machines r where not exists (select 1 from live_entities v "
            "where v.entity_id = r.entity_id) returning r.machine_id"
        ).fetchall()
        self.triggers.update(m for (m,) in freed)
        self.cur.execute(
            "delete from satisfied_alt_groups g where not exists (select 1 from live_entities v "
            "where v.entity_id = g.entity_id)"
        )
        return len(ended)

    # ------------------------------------------------------------------ the scheduling pass

    def candidates(self, machines: list[str] | None) -> list[Candidate]:
        """Per machine (None: every machine), the first few bindable requests in the policy's order.

        One round trip (sql msched_candidates): the function reads which machines are usable itself,
        so the machines bound by an earlier round of this pass are no longer.
        """
        rows = self.cur.execute(
            "select * from msched_candidates(%s, %s, %s)", (machines, list(UP), self.per_machine)
        ).fetchall()
        unique = {
            int(k): Candidate(int(k), int(e), op, int(p), int(s), at, tuple(x[: -len(op) - 1] for x in slots))
            for k, e, op, p, s, at, slots in rows
        }
        return list(unique.values())

    def schedule(self) -> list[Outcome]:
        """Bind every request that can be bound now, in the policy's order; return what was bound.

        One round trip (sql msched_pass): per trigger machine the first few candidates in the
        policy's order (request_machines.rank, then seq), bound greedily; a machine whose candidates
        were all blocked (their other machine taken, their entity served) gets its next few in the
        next round, until a round binds nothing. The result is the greedy pass over the whole queue,
        at the cost of the few requests looked at. It ran from here, a round trip per round and one
        more that found nothing, until sql/096_sched_pass.sql moved it into the database.
        """
        trig, self.triggers = self.triggers, set()
        full, self.full = self.full, False
        if not trig and not full:
            return []
        rows = self.cur.execute(
            "select * from msched_pass(%s, %s, %s)", (None if full else sorted(trig), list(UP), self.per_machine)
        ).fetchall()
        ended = [Outcome.of(r) for r in rows]
        self.outcomes += ended
        return [o for o in ended if o.ack_code == AckCode.ACK_OK]

    # ------------------------------------------------------------------ moving requests out of the queue

    def _end_queued(
        self, cond: str, params: Sequence[Any], ack_code: str, note: str | None, held: bool = False
    ) -> list[Outcome]:
        """Move the queued requests matching cond to REQUEST_OUTCOMES; those not held are to be told."""
        rows = self.cur.execute(
            f"with gone as (delete from request_machines where {cond} returning *) "
            "insert into request_outcomes (request_key, entity_id, op_type, machines, ack_code, note, held, "
            "                              reply_to, reply_conv) "
            "select request_key, min(entity_id), min(op_type), array_agg(machine_id order by seq), %s, %s, %s, "
            "       min(reply_to), min(reply_conv) "
            f"from gone group by request_key returning {_OUTCOME_COLS}",
            [*params, ack_code, note, held],
        ).fetchall()
        ended = [Outcome.of(r) for r in rows]
        if not held:
            self.outcomes += ended
        return ended

    def _release_held(self, cond: str, params: Sequence[Any], ack_code: str, note: str | None) -> list[Outcome]:
        """Held outcomes matching cond become ack_code (note, if given) and are to be told."""
        rows = self.cur.execute(
            f"update request_outcomes set held = false, ack_code = %s, note = coalesce(%s, note) "
            f"where held and {cond} returning {_OUTCOME_COLS}",
            [ack_code, note, *params],
        ).fetchall()
        ended = [Outcome.of(r) for r in rows]
        self.outcomes += ended
        return ended

    def _settle(self, entities: set[int]) -> None:
        """An entity with held outcomes and nothing left queued has lost its last alternative: NO_MACHINE."""
        if entities:
            self._release_held(
                "entity_id = any(%s) and not exists (select 1 from request_machines q "
                "where q.entity_id = request_outcomes.entity_id)",
                [sorted(entities)],
                AckCode.NO_MACHINE,
                None,
            )


# Whether a sweep could change anything: a request queued (a pass, a machine down, an orphan), a machine
# reserved (its entity may have finished), a satisfied group of an entity that finished. A resting cell
# has none: its sweep is this one statement, not a transaction of eight round trips every sweep_s.
SWEEP_WORK = (
    "select exists (select 1 from request_machines) or exists (select 1 from reserved_machines) "
    "or exists (select 1 from satisfied_alt_groups g where not exists "
    "           (select 1 from live_entities v where v.entity_id = g.entity_id))"
)


@dataclass(frozen=True)
class StepDone:
    """What a committed step did: the machines each Unreserve_Me freed, each op's result, the outcomes to tell."""

    freed: list[list[str]]
    results: list[Any]
    outcomes: list[Outcome]


def step(
    policy: Policy,
    frees: Sequence[tuple[int, str | None]] = (),
    finished: Sequence[int] = (),
    ops: Sequence[Callable[[Step], Any]] = (),
) -> Callable[[psycopg.Cursor[Any]], StepDone]:
    """A step for gwc.db.transaction: the frees (Unreserve_Me), then forgetting the `finished` outcomes,
    then the ops in order, then one scheduling pass.

    Without ops (the scheduler's step under load: lots freeing machines, entities acknowledging) the
    step is ONE statement (sql msched_step), which gwc.db.transaction runs alone in autocommit: one
    round trip instead of BEGIN, a statement per change, the pass and COMMIT. PostgreSQL makes the
    statement atomic, so a decision is still committed before it is told.
    """
    if not ops:
        n = len(frees)

        def into(rows: list[tuple[Any, ...]]) -> StepDone:
            freed: list[list[str]] = [[] for _ in range(n)]
            outcomes: list[Outcome] = []
            for kind, i, machine, *outcome in rows:
                if kind == "freed":
                    freed[i - 1].append(machine)
                else:
                    outcomes.append(Outcome.of(outcome))
            return StepDone(freed, [], outcomes)

        return Statement(
            "select * from msched_step(%s::bigint[], %s::text[], %s::bigint[], %s::text[], false, %s, %s)",
            ([e for e, _ in frees], [m for _, m in frees], list(finished), [], list(UP), PER_MACHINE),
            fetch="all",
            into=into,
        )

    def run(cur: psycopg.Cursor[Any]) -> StepDone:
        s = Step(cur, policy)
        freed = s.unreserve_all(frees) if frees else []
        if finished:
            s.finish(finished)
        results = [op(s) for op in ops]
        s.schedule()
        return StepDone(freed, results, s.outcomes)

    return run
