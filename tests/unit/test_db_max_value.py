"""get_new_max_value: unique, strictly increasing ids per type, even under concurrent callers."""

from __future__ import annotations

import itertools
import multiprocessing
from typing import Any

import psycopg
import pytest

from gwc import db

PROCESSES = 8
CALLS = 500


def _take_ids(url: str, kind: str, calls: int, queue: Any) -> None:
    """One caller process: its own connection, one short transaction per id, as a module would."""
    taken = []
    with psycopg.connect(url) as conn:
        conn.execute("set role gwc_msched")
        conn.commit()
        for _ in range(calls):
            taken.append(db.get_new_max_value(conn, kind))
            conn.commit()
    queue.put(taken)


def test_eight_processes_get_unique_increasing_ids(database_url: str) -> None:
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_take_ids, args=(database_url, "MACH_R_KEY", CALLS, queue)) for _ in range(PROCESSES)]
    for p in procs:
        p.start()
    try:
        results = [queue.get(timeout=120) for _ in procs]
    finally:
        for p in procs:
            p.join(30)
            if p.is_alive():
                p.kill()
    every = [v for r in results for v in r]
    assert len(every) == PROCESSES * CALLS
    assert len(set(every)) == len(every), "an id was handed out twice"
    assert sorted(every) == list(range(1, PROCESSES * CALLS + 1)), "ids have gaps or do not start at 1"
    for r in results:  # each caller sees its own ids strictly increase
        assert all(a < b for a, b in itertools.pairwise(r))


def test_types_count_independently_and_rollback_gives_the_id_back(db_conn: psycopg.Connection[Any]) -> None:
    assert db.get_new_max_value(db_conn, "LOT_ID") == 1
    assert db.get_new_max_value(db_conn, "ENTITY_ID") == 1
    db_conn.commit()
    assert db.get_new_max_value(db_conn, "LOT_ID") == 2
    db_conn.rollback()
    assert db.get_new_max_value(db_conn, "LOT_ID") == 2
    assert db.get_new_max_value(db_conn, "NEW_KIND") == 1


def test_an_empty_type_is_refused(db_conn: psycopg.Connection[Any]) -> None:
    with pytest.raises(psycopg.errors.InvalidParameterValue):
        db.get_new_max_value(db_conn, "")


def test_module_roles_cannot_write_the_counters_directly(db_conn: psycopg.Connection[Any]) -> None:
    db_conn.execute("set role gwc_ls")
    with pytest.raises(psycopg.errors.InsufficientPrivilege):
        db_conn.execute("update max_values set value = 0")


def test_several_values_at_once_continue_the_same_counter(db_conn: psycopg.Connection[Any]) -> None:
    """get_new_max_values(type, n): one update hands out n values; the caller's end at the one returned."""
    assert db.get_new_max_value(db_conn, "MACH_R_ID") == 1
    assert db_conn.execute("select get_new_max_values('MACH_R_ID', 5)").fetchone()[0] == 6  # 2..6 are ours
    assert db.get_new_max_value(db_conn, "MACH_R_ID") == 7
    assert db_conn.execute("select get_new_max_values('FRESH', 3)").fetchone()[0] == 3  # a new type: 1..3
    with pytest.raises(psycopg.errors.InvalidParameterValue):
        db_conn.execute("select get_new_max_values('MACH_R_ID', 0)")
