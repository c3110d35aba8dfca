"""The scheduler on random request/free/shutdown/accept/cancel/finish sequences, against the real database.

After every step: no machine reserved twice, nothing bound to a machine that was not up, free and
accepting the request's op type, FIFO kept among requests that could have been bound together, no
request left queued that could be bound now, NO_MACHINE told only when the entity has no alternative
left, nothing bound to a finished entity, an alternative group (entity, alt_group) bound at most once
and a request of a bound group refused REQ_CANCEL; and at the end every request ended exactly once.
"""

from __future__ import annotations

import random
from collections import Counter
from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.ipc.codes import AckCode
from gwc.msched.policy import Fifo, Policy, Priority
from gwc.msched.store import UP, Outcome, Step

MACHINES = ["wc1", "wc2", "wc3", "wc4", "wc5", "wc6", "mazak"]
OP_TYPES = ["dummy_op", "measure", "mill_chess"]
ENTITIES = list(range(1, 31))
STATUSES = ["Idle", "Idle", "Running", "Setup", "Shutdown", "Run_Shut"]
GROUPS = [None, None, "g1", "g2"]  # Machine_Request.alt_group


def _setup(admin: psycopg.Connection[Any]) -> None:
    admin.execute("insert into lots (lot_id, product_id) values (1, 'alum_chess_set')")
    for e in ENTITIES:
        admin.execute("insert into lot_entities (entity_id, lot_id) values (%s, 1)", (e,))
        admin.execute("insert into lot_status (entity_id, lot_id, state) values (%s, 1, 'waiting_machine')", (e,))
        admin.execute("update lots set priority = 20")
    admin.execute("update machine_status set status = 'Idle' where machine_id = any(%s)", (MACHINES,))


class World:
    """What the test knows of the cell, to check each step against."""

    def __init__(self, cur: psycopg.Cursor[Any]) -> None:
        self.cur = cur

    def status(self) -> dict[str, str]:
        return dict(self.cur.execute("select machine_id, status from machine_status"))

    def accepts(self) -> set[tuple[str, str]]:
        return set(self.cur.execute("select machine_id, op_type from accept_types"))

    def reserved(self) -> dict[str, int]:
        return dict(self.cur.execute("select machine_id, entity_id from reserved_machines"))

    def queue(self) -> list[tuple[int, int, str, int, tuple[str, ...]]]:
        """(key, entity, op_type, seq, machines) oldest first."""
        return [
            (k, e, op, s, tuple(ms))
            for k, e, op, s, ms in self.cur.execute(
                "select request_key, min(entity_id), min(op_type), min(seq), array_agg(machine_id order by seq) "
                "from request_machines group by request_key order by 4"
            )
        ]

    def finished(self) -> set[int]:
        return {e for (e,) in self.cur.execute("select entity_id from lot_status where state = 'completed'")}

    def groups(self) -> set[tuple[int, str]]:
        return set(self.cur.execute("select entity_id, alt_group from satisfied_alt_groups"))

    def satisfiable(self) -> list[tuple[int, int, str, int, tuple[str, ...]]]:
        status, acc, res, done = self.status(), self.accepts(), self.reserved(), self.finished()
        return [
            q
            for q in self.queue()
            if q[1] not in done and all(status[m] in UP and m not in res and (m, q[2]) in acc for m in q[4])
        ]


def _random_op(rng: random.Random, w: World, admin: psycopg.Connection[Any]) -> tuple[str, Any]:
    """Pick the next event; the database side of it (a status change) is done here, as MS would."""
    kind = rng.choices(
        ["request", "free", "status", "accept", "cancel", "ack", "finish", "sweep"], [8, 4, 2, 2, 1, 2, 0.5, 1]
    )[0]
    if kind == "request":
        n = rng.choice([1, 1, 2])
        return kind, (rng.choice(ENTITIES), rng.choice(OP_TYPES), rng.sample(MACHINES, n), rng.choice(GROUPS))
    if kind == "finish":  # an entity completes, as the Lot Server records it, mostly one with requests waiting
        q = w.queue()
        e = rng.choice(q)[1] if q and rng.random() < 0.8 else rng.choice(ENTITIES)
        admin.execute("update lot_status set state = 'completed' where entity_id = %s", (e,))
        return kind, e
    if kind == "free":
        res = w.reserved()
        if not res:
            return "noop", None
        m = rng.choice(sorted(res))
        return kind, (res[m], None if rng.random() < 0.5 else m)
    if kind == "status":
        m, st = rng.choice(MACHINES), rng.choice(STATUSES)
        admin.execute("update machine_status set status = %s where machine_id = %s", (st, m))
        return kind, (m, st)
    if kind == "accept":
        m = rng.choice(MACHINES)
        return kind, (m, ["*"] if rng.random() < 0.5 else rng.sample(OP_TYPES, rng.randint(0, 2)))
    if kind == "cancel":
        q = w.queue()
        if not q:
            return "noop", None
        key, entity = rng.choice(q)[:2]
        return kind, (key, None) if rng.random() < 0.7 else (None, entity)
    return kind, None


def _apply(step: Step, kind: str, arg: Any, told: list[Outcome]) -> Any:
    if kind == "request":
        entity, op, machines, group = arg
        return step.queue_request(entity, op, machines, None, "lot:test", None, group)
    if kind == "free":
        step.unreserve(*arg)
    elif kind == "status":
        machine, status = arg
        if status == "Shutdown":
            step.machines_down()
        elif status in UP:
            step.machine_up(machine)
    elif kind == "accept":
        step.set_accept_types(*arg)
    elif kind == "cancel":
        step.cancel(*arg, by="test")
    elif kind == "ack" and told:
        step.finish([o.request_key for o in told])
        told.clear()
    elif kind == "sweep":
        step.sweep()
    return None


def _run(conn: psycopg.Connection[Any], admin: psycopg.Connection[Any], policy: Policy, seed: int, steps: int) -> None:
    rng = random.Random(seed)
    ended: Counter[int] = Counter()
    codes: Counter[str] = Counter()
    queued_ever: set[int] = set()
    told: list[Outcome] = []
    group_of: dict[int, tuple[int, str]] = {}  # request_key -> its (entity, alt_group)
    satisfied: set[tuple[int, str]] = set()  # the groups bound, and not forgotten by a sweep
    for i in range(steps):
        with conn.transaction(), conn.cursor() as cur:
            w = World(cur)
            kind, arg = _random_op(rng, w, admin)
            step = Step(cur, policy, per_machine=1 if i % 2 else 3)  # small rounds: stress the repeat
            before_q = {q[0] for q in w.queue()}
            done = w.finished()
            result = _apply(step, kind, arg, told)
            where = f"seed {seed} step {i} ({kind} {arg})"
            if kind == "request":
                entity, _, _, group = arg
                served = entity not in done and (entity, group) in satisfied
                assert (result.ack_code == AckCode.REQ_CANCEL) == served, f"{where}: {result}"
                if result.ack_code == AckCode.ACK_OK and group is not None:
                    group_of[result.request_key] = (entity, group)
                if served:
                    assert {q[0] for q in w.queue()} == before_q, f"{where}: a served group's request was queued"
            if kind == "sweep":
                assert not {q[1] for q in w.queue()} & done, f"{where}: a finished entity's request still waits"
                satisfied = {g for g in satisfied if g[0] not in done}
            queued_ever |= {q[0] for q in w.queue()} | before_q
            # The state the pass sees: after the step's changes, before binding.
            status, acc, res_before = w.status(), w.accepts(), w.reserved()
            sat = w.satisfiable()
            bound = step.schedule()
            res_after = w.reserved()
            for o in bound:
                assert o.entity_id not in done, f"{where}: bound a request of finished entity {o.entity_id}"
                if o.request_key in group_of:
                    assert group_of[o.request_key] not in satisfied, f"{where}: a group bound twice"
                    satisfied.add(group_of[o.request_key])
                q = next(q for q in sat if q[0] == o.request_key)
                for m in o.machines:
                    assert status[m] in UP, f"{where}: bound {m} which is {status[m]}"
                    assert m not in res_before, f"{where}: {m} was reserved already"
                    assert (m, q[2]) in acc, f"{where}: {m} does not accept {q[2]}"
                    assert res_after[m] == o.entity_id, where
            assert sum(len(o.machines) for o in bound) == len(res_after) - len(res_before), (
                f"{where}: a machine reserved twice"
            )
            if isinstance(policy, Fifo):  # an older request that could be bound lost only to an older one
                keys = {o.request_key for o in bound}
                for q in sat:
                    if q[0] in keys:
                        continue
                    blockers = [
                        b for b in sat if b[0] in keys and b[3] < q[3] and (set(b[4]) & set(q[4]) or b[1] == q[1])
                    ]
                    assert blockers, f"{where}: request {q[0]} could be bound and no older request took its place"
            assert w.satisfiable() == [], f"{where}: a request that could be bound is left waiting"
            assert w.groups() == satisfied, f"{where}: satisfied_alt_groups is not what was bound"
            queue_entities = {q[1] for q in w.queue()}
            for o in step.outcomes:
                ended[o.request_key] += 1
                codes[o.ack_code] += 1
                if o.ack_code == AckCode.NO_MACHINE:
                    assert o.entity_id not in queue_entities, f"{where}: NO_MACHINE told with an alternative alive"
            told += step.outcomes
    with conn.transaction(), conn.cursor() as cur:  # MSCHED shuts down: the rest end NO_MACHINE
        step = Step(cur, policy)
        step.shutdown_all("end of test")
        for o in step.outcomes:
            ended[o.request_key] += 1
    assert set(ended) == queued_ever, "a request never ended"
    assert min(codes[c] for c in (AckCode.ACK_OK, AckCode.REQ_CANCEL, AckCode.NO_MACHINE)) >= 1, codes  # all paths ran
    assert max(ended.values(), default=1) == 1, [k for k, n in ended.items() if n > 1]


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_random_sequences_fifo(cell_config: Config, database_url: str, seed: int) -> None:
    with psycopg.connect(database_url, autocommit=True) as admin, db.connect(cell_config, role="msched") as conn:
        _setup(admin)
        conn.autocommit = True  # each step is its own explicit transaction
        _run(conn, admin, Fifo(), seed, 250)


def test_random_sequences_priority(cell_config: Config, database_url: str) -> None:
    with psycopg.connect(database_url, autocommit=True) as admin, db.connect(cell_config, role="msched") as conn:
        _setup(admin)
        conn.autocommit = True
        _run(conn, admin, Priority(ageing_s=5), 7, 250)
