"""MSCHED's store, piece by piece against the real database: batched frees, the policy's rank stored
with each request (and set again when the policy changes), the candidate walk, the statistics refresh.

The random sequences of test_msched_property.py check the pass as a whole; these check the parts the
scheduler's speed rests on, which those sequences would only notice indirectly.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.ipc.codes import AckCode
from gwc.msched import store
from gwc.msched.policy import Fifo, Policy, Priority
from gwc.msched.store import SWEEP_WORK, Step

MACHINES = ["wc1", "wc2", "wc3"]


@pytest.fixture
def conn(cell_config: Config, database_url: str) -> Iterator[psycopg.Connection[Any]]:
    """MSCHED's connection (role gwc_msched) to a database with entities 1..20 and wc1..wc3 Idle."""
    with psycopg.connect(database_url, autocommit=True) as admin:
        admin.execute("insert into lots (lot_id, product_id) values (1, 'alum_chess_set')")
        admin.execute("insert into lot_entities (entity_id, lot_id) select g, 1 from generate_series(1, 20) g")
        admin.execute(
            "insert into lot_status (entity_id, lot_id, state) select g, 1, 'waiting_machine' "
            "from generate_series(1, 20) g"
        )
        admin.execute("update machine_status set status = 'Idle' where machine_id = any(%s)", (MACHINES,))
    with db.connect(cell_config, role="msched") as c:
        c.autocommit = True
        yield c


def _step(conn: psycopg.Connection[Any], policy: Policy, fn: Any) -> tuple[Any, Step]:
    with conn.transaction(), conn.cursor() as cur:
        step = Step(cur, policy)
        result = fn(step)
        step.schedule()
        return result, step


def _accept_all(conn: psycopg.Connection[Any], policy: Policy) -> None:
    _step(conn, policy, lambda s: [s.set_accept_types(m, ["*"]) for m in MACHINES])


def test_frees_of_one_step_each_get_their_own_machines(conn: psycopg.Connection[Any]) -> None:
    fifo = Fifo()
    _accept_all(conn, fifo)
    _step(conn, fifo, lambda s: [s.queue_request(1, "dummy_op", ["wc1", "wc2"], None, "t", "c1")])
    _step(conn, fifo, lambda s: [s.queue_request(2, "dummy_op", ["wc3"], None, "t", "c2")])
    freed, _ = _step(conn, fifo, lambda s: s.unreserve_all([(1, "wc2"), (2, None), (1, "wc3"), (7, None), (1, None)]))
    # entity 1 frees wc2, then (all) the rest: wc1; wc3 was never entity 1's; entity 7 holds nothing
    assert freed == [["wc2"], ["wc3"], [], [], ["wc1"]]
    assert conn.execute("select count(*) from reserved_machines").fetchone()[0] == 0


def test_a_step_of_frees_and_acknowledgements_is_one_statement_that_frees_forgets_and_binds(
    conn: psycopg.Connection[Any],
) -> None:
    fifo = Fifo()
    _accept_all(conn, fifo)
    (held,), step = _step(conn, fifo, lambda s: [s.queue_request(1, "dummy_op", ["wc1", "wc2"], None, "t", "c1")])
    assert [o.ack_code for o in step.outcomes] == [AckCode.ACK_OK]  # entity 1 holds wc1 and wc2
    _step(
        conn,
        fifo,
        lambda s: [
            s.queue_request(e, "dummy_op", ms, None, "t", f"c{e}")
            for e, ms in ((2, ["wc1", "wc2"]), (3, ["wc2"]), (4, ["wc1"]))
        ],
    )
    # entity 1 acknowledged its outcome and frees wc1, then all the rest (wc2); entity 9 holds nothing
    work = store.step(fifo, frees=[(1, "wc1"), (1, None), (9, None)], finished=[held.request_key])
    assert isinstance(work, db.Statement)  # run alone, in autocommit: one round trip
    done = db.transaction(conn, work)
    assert done.freed == [["wc1"], ["wc2"], []]
    # the oldest, entity 2, takes both machines; 3 and 4 wait
    assert [(o.entity_id, o.ack_code, o.machines) for o in done.outcomes] == [(2, AckCode.ACK_OK, ("wc1", "wc2"))]
    assert (
        conn.execute("select count(*) from request_outcomes where request_key = %s", (held.request_key,)).fetchone()[0]
        == 0
    )
    assert dict(conn.execute("select machine_id, entity_id from reserved_machines")) == {"wc1": 2, "wc2": 2}
    # 2 frees wc2 only: 3 takes it; then wc1: 4 takes it
    done = db.transaction(conn, store.step(fifo, frees=[(2, "wc2")]))
    assert [(o.entity_id, o.machines) for o in done.outcomes] == [(3, ("wc2",))]
    done = db.transaction(conn, store.step(fifo, frees=[(2, "wc1")]))
    assert [(o.entity_id, o.machines) for o in done.outcomes] == [(4, ("wc1",))]
    # a step with other changes is a transaction of its own statements, the frees first
    work = store.step(fifo, frees=[(3, None)], ops=[lambda s: s.queue_request(5, "dummy_op", ["wc2"], None, "t", "c5")])
    assert not isinstance(work, db.Statement)
    done = db.transaction(conn, work)
    assert done.freed == [["wc2"]] and done.results[0].ack_code == AckCode.ACK_OK
    assert [(o.entity_id, o.machines) for o in done.outcomes] == [(5, ("wc2",))]


def test_a_machine_freed_or_accepting_again_with_nobody_waiting_makes_no_pass(conn: psycopg.Connection[Any]) -> None:
    fifo = Fifo()
    _accept_all(conn, fifo)
    _step(conn, fifo, lambda s: [s.queue_request(e, "dummy_op", ["wc1"], None, "t", f"c{e}") for e in (1, 2)])

    def triggers(op: Any) -> set[str]:  # what the step would pass over, before its pass
        with conn.transaction(), conn.cursor() as cur:
            step = Step(cur, fifo)
            op(step)
            return step.triggers

    # entity 1 holds wc1, entity 2 waits for it: freeing it or its accepting again is a pass's business
    _step(conn, fifo, lambda s: s.set_accept_types("wc1", []))
    assert triggers(lambda s: s.set_accept_types("wc1", ["*"])) == {"wc1"}
    _, step = _step(conn, fifo, lambda s: s.unreserve(1, None))
    assert [o.entity_id for o in step.outcomes] == [2]
    # nobody waits now: neither is
    _step(conn, fifo, lambda s: s.set_accept_types("wc1", []))
    assert triggers(lambda s: s.set_accept_types("wc1", ["*"])) == set()
    assert triggers(lambda s: s.unreserve(2, None)) == set()
    assert triggers(lambda s: s.queue_request(3, "dummy_op", ["wc2"], None, "t", "c3")) == {"wc2"}


def test_priority_rank_is_stored_and_set_again_when_the_policy_changes(conn: psycopg.Connection[Any]) -> None:
    fifo, prio = Fifo(), Priority(ageing_s=10)
    # wc1 is held, so the requests queue: entity 3 asks first with priority 30, entity 4 later with 5
    _accept_all(conn, fifo)
    _step(conn, fifo, lambda s: s.queue_request(2, "dummy_op", ["wc1"], None, "t", "hold"))
    _step(conn, fifo, lambda s: s.queue_request(3, "dummy_op", ["wc1"], 30, "t", "c3"))
    _step(conn, fifo, lambda s: s.queue_request(4, "dummy_op", ["wc1"], 5, "t", "c4"))
    assert conn.execute("select array_agg(distinct rank) from request_machines").fetchone()[0] == [0.0]
    # MSCHED restarts with the priority policy: every waiting request gets its priority rank
    _step(conn, prio, lambda s: s.startup(clean=False))
    rows = conn.execute("select entity_id, priority, requested_at, rank from request_machines order by entity_id")
    for entity, priority, at, rank in rows:
        assert rank == pytest.approx(priority + at.timestamp() / 10), entity
    # freed, wc1 goes to the more urgent request, not the older one (FIFO would take entity 3)
    _, step = _step(conn, prio, lambda s: s.unreserve(2, None))
    assert [o.entity_id for o in step.outcomes] == [4]
    # a request queued under priority is ranked as it is queued
    _step(conn, prio, lambda s: s.queue_request(5, "dummy_op", ["wc1"], 1, "t", "c5"))
    rank, at = conn.execute("select rank, requested_at from request_machines where entity_id = 5").fetchone()
    assert rank == pytest.approx(1 + at.timestamp() / 10)


def test_candidates_are_the_first_few_bindable_of_each_machine_in_order(conn: psycopg.Connection[Any]) -> None:
    fifo = Fifo()
    _accept_all(conn, fifo)
    holders = {"wc1": 1, "wc2": 8, "wc3": 9}
    _step(conn, fifo, lambda s: [s.queue_request(e, "dummy_op", [m], None, "t", f"h{m}") for m, e in holders.items()])
    # behind the holders: on wc1, entity 2 wants wc1+wc2 (blocked while wc2 is held), then 3..7 want wc1
    _step(conn, fifo, lambda s: s.queue_request(2, "dummy_op", ["wc1", "wc2"], None, "t", "c2"))
    _step(conn, fifo, lambda s: [s.queue_request(e, "dummy_op", ["wc1"], None, "t", f"c{e}") for e in range(3, 8)])
    with psycopg.connect(conn.info.dsn, autocommit=True) as admin:  # entity 4 finishes meanwhile
        admin.execute("update lot_status set state = 'completed' where entity_id = 4")
    with conn.transaction(), conn.cursor() as cur:
        step = Step(cur, fifo, per_machine=2)
        assert step.candidates(["wc1"]) == []  # wc1 is held
        step.unreserve(1, None)
        cands = step.candidates(["wc1"])
        # entity 2's request is blocked (wc2 not usable), entity 4 finished: the first two others
        assert [c.entity_id for c in cands] == [3, 5]
        assert all(c.machines == ("wc1",) for c in cands)
        step.unreserve(8, None)
        both = step.candidates(["wc1"])
        assert [c.entity_id for c in both] == [2, 3]
        assert [c.entity_id for c in step.candidates(None)] == [2, 3]  # every machine: wc3 is held
        assert both[0].machines == ("wc1", "wc2")


def _pass_walks(
    database_url: str, freed_by: list[int], machines: list[str], per: int
) -> tuple[list[tuple[int, str]], int]:
    """Free the machines of `freed_by` and run msched_pass over `machines` in a transaction rolled
    back: (entity, ack_code) of each outcome, and how many times the pass walked the queue."""
    with psycopg.connect(database_url) as admin:
        admin.execute("set track_functions = 'all'")
        admin.execute("delete from reserved_machines where entity_id = any(%s)", (freed_by,))
        rows = admin.execute(
            "select entity_id, ack_code from msched_pass(%s, %s, %s)", (machines, list(store.UP), per)
        ).fetchall()
        walks = admin.execute(
            "select coalesce(sum(calls), 0) from pg_stat_xact_user_functions where funcname = 'msched_walk'"
        ).fetchone()
        admin.rollback()
    return [(int(e), str(a)) for e, a in rows], int(walks[0] if walks else 0)


def test_the_pass_walks_again_only_the_machines_whose_walk_stopped_at_its_limit(
    conn: psycopg.Connection[Any], database_url: str
) -> None:
    fifo = Fifo()
    _accept_all(conn, fifo)
    holders = {"wc1": 10, "wc2": 11, "wc3": 12}
    _step(conn, fifo, lambda s: [s.queue_request(e, "dummy_op", [m], None, "t", f"h{m}") for m, e in holders.items()])
    # queued, oldest first: entity 4 wants wc2; entity 2 wants wc1+wc2; entity 3 wants wc1; entity 5
    # wants wc2+wc3
    for e, ms in ((4, ["wc2"]), (2, ["wc1", "wc2"]), (3, ["wc1"]), (5, ["wc2", "wc3"])):
        _step(conn, fifo, lambda s, e=e, ms=ms: s.queue_request(e, "dummy_op", ms, None, "t", f"c{e}"))
    # All three freed, one candidate a machine: wc1 gives entity 2, wc2 entity 4, wc3 entity 5. Entity 4
    # takes wc2, which blocks 2 and 5. Every walk stopped at its limit, so wc1 and wc3 are walked again:
    # wc1 gives 3, bound; wc3 gives nothing (5 is blocked), and its walk reached the end of its queue:
    # it is not walked a third time.
    bound, walks = _pass_walks(database_url, [10, 11, 12], MACHINES, per=1)
    assert sorted(e for e, a in bound if a == AckCode.ACK_OK) == [3, 4]
    assert walks == 2
    # Four a machine: wc1 gives 2 and 3, wc2 gives 4, 2 and 5, wc3 gives 5, all fewer than four: every
    # walk reached the end of its queue. Entity 4 takes wc2 and 3 takes wc1; wc3 is left free, and no
    # round walks it again for nothing.
    bound, walks = _pass_walks(database_url, [10, 11, 12], MACHINES, per=4)
    assert sorted(e for e, a in bound if a == AckCode.ACK_OK) == [3, 4]
    assert walks == 1


def test_the_candidate_walk_is_planned_once_a_session(conn: psycopg.Connection[Any]) -> None:
    # sql/020_procedures.sql: a LANGUAGE sql function with SET clauses is planned at every call (0.55 ms of
    # its 0.63); PL/pgSQL keeps the plan for the session, and its SET clauses make the generic plan the
    # same index walk (gwc bench sched measures it at 10,000 queued). msched_walk is the one walk: the
    # pass (msched_pass) and msched_candidates both read it.
    lang, config = conn.execute(
        "select l.lanname, p.proconfig from pg_proc p join pg_language l on l.oid = p.prolang "
        "where p.proname = 'msched_walk'"
    ).fetchone() or (None, None)
    assert lang == "plpgsql"
    assert "plan_cache_mode=force_generic_plan" in config and "enable_sort=off" in config


def test_queue_statistics_are_refreshed_only_when_much_changed(conn: psycopg.Connection[Any]) -> None:
    fifo = Fifo()
    _accept_all(conn, fifo)

    def analyze() -> bool:
        conn.execute("select pg_stat_force_next_flush()")  # this backend's counters, visible now
        conn.execute("select pg_stat_clear_snapshot()")
        return bool(_step(conn, fifo, lambda s: s.analyze())[0])

    _step(conn, fifo, lambda s: s.queue_request(1, "dummy_op", ["wc1"], None, "t", "hold"))
    _step(
        conn, fifo, lambda s: [s.queue_request(e % 20 + 1, "dummy_op", ["wc1"], None, "t", f"c{e}") for e in range(5)]
    )
    assert analyze() is False  # a few rows since the database was made: no need
    _step(
        conn, fifo, lambda s: [s.queue_request(e % 20 + 1, "dummy_op", ["wc1"], None, "t", f"d{e}") for e in range(300)]
    )
    assert analyze() is True
    assert analyze() is False  # just done
    assert conn.execute(
        "select last_analyze is not null from pg_stat_user_tables where relname = 'request_machines'"
    ).fetchone()[0]


def test_a_refused_request_is_neither_queued_nor_given_a_key(conn: psycopg.Connection[Any]) -> None:
    """Each refusal says which check failed, and only a request that passes them all is queued (and
    takes a MACH_R_KEY); a repeat of the conversation gets its first answer."""
    fifo = Fifo()
    with psycopg.connect(conn.info.dsn, autocommit=True) as admin:
        admin.execute("update lot_status set state = 'exported' where entity_id = 2")
        admin.execute("insert into satisfied_alt_groups (entity_id, alt_group, request_key) values (3, 'g', 77)")
        admin.execute("update machine_status set status = 'Shutdown' where machine_id = 'wc3'")

    def key() -> int:
        return int(conn.execute("select value from max_values where type = 'MACH_R_KEY'").fetchone()[0])

    before = key()
    refusals = {
        (99, "dummy_op", ("wc1",), None): (AckCode.UNKNOWN, "entity 99 is not known to the Lot Server"),
        (2, "dummy_op", ("wc1",), None): (AckCode.NOTNOW, "entity 2 is exported: it cannot ask for machines"),
        (3, "dummy_op", ("wc1",), "g"): (AckCode.REQ_CANCEL, "alternative 77 already satisfied"),
        (4, "no_such_op", ("wc1",), None): (AckCode.UNKNOWN, "op type 'no_such_op' is not known"),
        (5, "dummy_op", ("wc1", "wc9"), None): (AckCode.NO_MACHINE, "machine wc9 does not exist (ME_CONFIG)"),
        (6, "dummy_op", ("wc1", "wc3"), None): (AckCode.NO_MACHINE, "machine wc3 is Shutdown"),
    }
    for (e, op, machines, group), want in refusals.items():
        got, _ = _step(conn, fifo, lambda s, a=(e, op, machines, None, "t", f"r{e}", group): s.queue_request(*a))
        assert (got.ack_code, got.note) == want
    assert key() == before
    assert conn.execute("select count(*) from request_machines").fetchone()[0] == 0

    first, _ = _step(conn, fifo, lambda s: s.queue_request(7, "dummy_op", ["wc1", "wc2"], 4, "t", "ok", "h"))
    again, _ = _step(conn, fifo, lambda s: s.queue_request(7, "dummy_op", ["wc1", "wc2"], 4, "t", "ok", "h"))
    assert (first.ack_code, first.request_key) == (AckCode.ACK_OK, before + 1)
    assert (again.ack_code, again.request_key, again.note) == (AckCode.ACK_OK, before + 1, "already queued")
    assert key() == before + 1
    rows = conn.execute("select machine_id, priority, alt_group from request_machines order by seq").fetchall()
    assert rows == [("wc1", 4, "h"), ("wc2", 4, "h")]  # queued, not bound: the machines accept nothing yet


def test_a_sweep_is_looked_for_only_where_it_could_change_something(conn: psycopg.Connection[Any]) -> None:
    """store.SWEEP_WORK: a resting cell (nothing queued, reserved or remembered of a finished entity)
    is not swept; any one of them is."""

    def needed() -> bool:
        return bool(conn.execute(SWEEP_WORK).fetchone()[0])

    fifo = Fifo()
    assert not needed()
    _step(conn, fifo, lambda s: s.queue_request(1, "dummy_op", ["wc1"], None, "t", "q"))
    assert needed()  # queued (the machines accept nothing yet)
    _accept_all(conn, fifo)
    assert conn.execute("select count(*) from reserved_machines").fetchone()[0] == 1
    assert needed()  # bound now: reserved
    _step(conn, fifo, lambda s: s.unreserve(1, None))
    with psycopg.connect(conn.info.dsn, autocommit=True) as admin:
        admin.execute("insert into satisfied_alt_groups (entity_id, alt_group, request_key) values (2, 'g', 9)")
        assert not needed()  # entity 2 is alive: its group is remembered on purpose
        admin.execute("update lot_status set state = 'exported' where entity_id = 2")
    assert needed()
    _step(conn, fifo, lambda s: s.sweep())
    assert not needed()
