"""The Machine Server's store (gwc/servers/machine_store.py) on the template database, without a bus:
a change made only from a status that allows it (and recorded with it), the machine's books (runs,
scrap once per report, maintenance), a downtime's reason, and the refusals (Refused) of what the tables
do not hold."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.errors import Refused
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.servers import machine_store

T = TypeVar("T")
UP = set(MachineStatus) - {MachineStatus.SHUTDOWN}


@pytest.fixture
def ms(cell_config: Config) -> Iterator[psycopg.Connection[Any]]:
    """The Machine Server's own connection (role gwc_ms)."""
    with db.connect(cell_config, role="ms") as c:
        yield c


def runner(conn: psycopg.Connection[Any]) -> Callable[[Callable[[Any], T]], T]:
    return lambda fn: db.transaction(conn, fn)


def test_every_configured_machine_is_loaded_with_its_maintenance_interval(ms: psycopg.Connection[Any]) -> None:
    watched = runner(ms)(lambda cur: machine_store.load(cur, {"wc1": 5}))
    by_id = {w.machine_id: w for w in watched}
    assert {"cmm_wc", "wc1"} <= set(by_id)
    assert by_id["wc1"].status == MachineStatus.SHUTDOWN and by_id["wc1"].liveness == 3.0
    assert ms.execute("select maintenance_every from machine_status where machine_id = 'wc1'").fetchone() == (5,)


def test_a_change_is_made_only_from_an_allowed_status_and_recorded_with_it(ms: psycopg.Connection[Any]) -> None:
    run = runner(ms)
    fields = {"record": True, "e10": "unscheduled_downtime"}
    went = machine_store.change(run, "wc1", MachineStatus.IDLE, {MachineStatus.SHUTDOWN}, note="up", **fields)
    assert went == machine_store.Change(MachineStatus.SHUTDOWN, None, True)
    refused = machine_store.change(run, "wc1", MachineStatus.RUNNING, {MachineStatus.SETUP}, **fields)
    assert refused == machine_store.Change(MachineStatus.IDLE, None, False)
    down = machine_store.change(run, "wc1", MachineStatus.SHUTDOWN, UP, note="operator stop", **fields)
    assert down is not None and down.changed and down.previous == MachineStatus.IDLE
    causes = ms.execute(
        "select status, cause from machine_state_history where machine_id = 'wc1' order by 1"
    ).fetchall()
    assert ("Idle", "start") in causes and ("Shutdown", "operator_stop") in causes
    assert ms.execute("select count(*) from downtime_events where machine_id = 'wc1' and ended_at is null").fetchone()
    assert machine_store.change(run, "nope", MachineStatus.IDLE, {MachineStatus.SHUTDOWN}, **fields) is None


def test_status_and_liveness_are_read_and_an_unknown_machine_is_refused(ms: psycopg.Connection[Any]) -> None:
    run = runner(ms)
    got = run(machine_store.status("wc1"))
    assert got.status == "Shutdown" and got.machine_run_id is None
    assert run(machine_store.liveness("wc1")) == 3.0 and run(machine_store.liveness("nope")) == 3.0
    with pytest.raises(Refused) as refused:
        run(machine_store.status("nope"))
    assert refused.value.ack_code == AckCode.UNKNOWN and "no machine 'nope'" in refused.value.detail


def test_runs_count_toward_maintenance_and_maintenance_starts_the_count_again(
    ms: psycopg.Connection[Any],
) -> None:
    run = runner(ms)
    run(lambda cur: machine_store.load(cur, {"wc1": 2}))
    assert run(machine_store.count_run("wc1")) == machine_store.RunCount(1, 2)
    assert run(machine_store.count_run("wc1")) == machine_store.RunCount(2, 2)
    assert run(machine_store.count_run("nope")) is None
    assert run(machine_store.maintained("wc1", "op", True)) == 2
    assert run(machine_store.count_run("wc1")).runs == 1
    with pytest.raises(Refused) as refused:
        run(machine_store.maintained("nope", "op", True))
    assert refused.value.ack_code == AckCode.UNKNOWN


def test_scrap_is_booked_once_per_report_of_a_run_the_machine_made(
    ms: psycopg.Connection[Any], db_conn: psycopg.Connection[Any]
) -> None:
    db_conn.execute(
        "insert into machine_run_outcome (machine_run_id, machine_id, ack_code) values (7, 'wc1', 'ACK_OK')"
    )
    db_conn.commit()
    run = runner(ms)
    assert run(lambda cur: machine_store.book_scrap(cur, 7, "wc1", 3, 2, "burr")) is True
    assert run(lambda cur: machine_store.book_scrap(cur, 7, "wc1", 3, 2, "burr")) is False
    assert ms.execute("select scrap_count from machine_status where machine_id = 'wc1'").fetchone() == (2,)
    with pytest.raises(Refused) as refused:
        run(lambda cur: machine_store.book_scrap(cur, 8, "wc1", 3, 1, None))
    assert refused.value.ack_code == AckCode.UNKNOWN and "no run 8 on wc1" in refused.value.detail


def test_a_downtime_gets_its_reason_and_an_unknown_one_is_refused(ms: psycopg.Connection[Any]) -> None:
    run = runner(ms)
    fields = {"record": True, "e10": "unscheduled_downtime"}
    machine_store.change(run, "wc1", MachineStatus.IDLE, {MachineStatus.SHUTDOWN}, **fields)
    machine_store.change(run, "wc1", MachineStatus.SHUTDOWN, UP, **fields)
    got = run(machine_store.downtime_reason("tooling", "op", "scheduled_downtime", None, "wc1"))
    assert got.machine_id == "wc1" and got.e10_state == "scheduled_downtime"
    with pytest.raises(Refused) as refused:
        run(machine_store.downtime_reason("tooling", "op", "scheduled_downtime", 999_999, None))
    assert refused.value.ack_code == AckCode.UNKNOWN and "no event 999999" in refused.value.detail


def test_a_change_names_its_run(ms: psycopg.Connection[Any]) -> None:
    run = runner(ms)
    fields = {"record": False, "e10": "unscheduled_downtime"}
    machine_store.change(run, "wc1", MachineStatus.IDLE, {MachineStatus.SHUTDOWN}, **fields)
    went = machine_store.change(run, "wc1", MachineStatus.SETUP, {MachineStatus.IDLE}, run=41, recipe_id="r", **fields)
    assert went == machine_store.Change(MachineStatus.IDLE, 41, True)
    assert run(machine_store.status("wc1")).machine_run_id == 41
