"""`gwc check`: every invariant the cell promises is reported when a real database breaks it.

Each breach is built by hand with the superuser connection (a test acts for no module), then the
checker must name exactly that invariant; the seeded, untouched database must pass.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc.check import Breach, check_cell, check_database, check_live, persistent
from gwc.config import Config
from gwc.ipc.bus import Peer
from tests.conftest import make_config

STARTED_WC = frozenset({"ME_START", "ME_SHUT", "SETUP_RUN", "START_RUN", "DNLD_ME", "UPLD_ME", "ALARM_CLE"})
IDLE_WC = frozenset({"ME_START", "ALARM_CLE"})
STARTED_SERVER = frozenset({"STARTUP", "SHUTDOWN", "MACH_REQ"})


def names(breaches: list[Breach]) -> set[str]:
    return {b.invariant for b in breaches}


def only(breaches: list[Breach], name: str) -> Breach:
    assert names(breaches) == {name}, breaches
    return breaches[0]


def lot(
    conn: psycopg.Connection[Any],
    entity: int,
    state: str = "waiting_machine",
    pid: int | None = None,
    destroyed: bool = False,
) -> None:
    """A lot with one entity in `state` (lot_id = entity), its script `pid`."""
    conn.execute("insert into lots (lot_id, quantity) values (%s, 1)", (entity,))
    conn.execute(
        "insert into lot_entities (entity_id, lot_id, unit, destroyed_at) values (%s, %s, 1, %s)",
        (entity, entity, "now" if destroyed else None),
    )
    conn.execute(
        "insert into lot_status (entity_id, lot_id, state, reason, script_pid) values (%s, %s, %s, %s, %s)",
        (entity, entity, state, "test" if state == "failed" else None, pid),
    )


def reserve(conn: psycopg.Connection[Any], machine: str, entity: int, run_id: int, key: int) -> None:
    conn.execute(
        "insert into reserved_machines (machine_id, entity_id, machine_run_id, request_key) values (%s, %s, %s, %s)",
        (machine, entity, run_id, key),
    )


def queue(conn: psycopg.Connection[Any], key: int, entity: int, machine: str) -> None:
    conn.execute(
        "insert into request_machines (request_key, entity_id, machine_id, op_type) values (%s, %s, %s, 'dummy_op')",
        (key, entity, machine),
    )


def machine_up(conn: psycopg.Connection[Any], *machines: str, status: str = "Idle") -> None:
    for m in machines:
        conn.execute("update machine_status set status = %s where machine_id = %s", (status, m))


@pytest.fixture
def dead_pid() -> int:
    """The pid of a process that has exited and been reaped."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_seeded_database_holds_every_invariant(db_conn: psycopg.Connection[Any]) -> None:
    assert check_database(db_conn) == []


def test_a_cell_in_mid_flight_holds_every_invariant(db_conn: psycopg.Connection[Any]) -> None:
    machine_up(db_conn, "wc1", "wc2", "wc3")
    lot(db_conn, 1, "running", pid=subprocess.os.getpid())
    reserve(db_conn, "wc1", 1, 100, 10)
    lot(db_conn, 2, "waiting_machine", pid=subprocess.os.getpid())
    queue(db_conn, 11, 2, "wc2")
    queue(db_conn, 12, 2, "wc3")
    lot(db_conn, 3, "exported")
    lot(db_conn, 4, "failed")
    lot(db_conn, 5, "created")
    db_conn.execute(
        "insert into machine_run_result (machine_run_id, machine_id, param, value) "
        "values (99, 'wc2', 'x', '1'), (99, 'wc2', 'y', '2')"
    )
    assert check_database(db_conn) == []


def test_machine_reserved_by_two_entities_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    db_conn.execute("alter table reserved_machines drop constraint reserved_machines_pkey")  # this test's clone only
    lot(db_conn, 1, pid=subprocess.os.getpid())
    lot(db_conn, 2, pid=subprocess.os.getpid())
    reserve(db_conn, "wc1", 1, 100, 10)
    reserve(db_conn, "wc1", 2, 101, 11)
    b = only(check_database(db_conn), "double_reservation")
    assert b.rows == [{"machine_id": "wc1", "entities": [1, 2]}]


def test_one_run_bound_to_two_entities_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    lot(db_conn, 1, pid=subprocess.os.getpid())
    lot(db_conn, 2, pid=subprocess.os.getpid())
    reserve(db_conn, "wc1", 1, 100, 10)
    reserve(db_conn, "wc2", 2, 100, 11)
    assert only(check_database(db_conn), "run_id_shared").rows == [{"machine_run_id": 100, "entities": [1, 2]}]


@pytest.mark.parametrize("state", ["completed", "waiting_export", "exported", "failed"])
def test_reservation_of_a_finished_entity_is_reported(db_conn: psycopg.Connection[Any], state: str) -> None:
    lot(db_conn, 1, state)
    reserve(db_conn, "wc1", 1, 100, 10)
    b = only(check_database(db_conn), "orphan_reservation")
    assert b.rows == [{"machine_id": "wc1", "entity_id": 1, "state": state}]


def test_reservation_and_request_of_a_destroyed_entity_are_reported(db_conn: psycopg.Connection[Any]) -> None:
    machine_up(db_conn, "wc2")
    lot(db_conn, 1, "running", pid=subprocess.os.getpid(), destroyed=True)
    reserve(db_conn, "wc1", 1, 100, 10)
    queue(db_conn, 11, 1, "wc2")
    assert names(check_database(db_conn)) == {"orphan_reservation", "orphan_request"}


def test_request_of_an_entity_without_status_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    machine_up(db_conn, "wc2")
    db_conn.execute("insert into lots (lot_id) values (7)")
    db_conn.execute("insert into lot_entities (entity_id, lot_id) values (7, 7)")
    queue(db_conn, 11, 7, "wc2")
    b = only(check_database(db_conn), "orphan_request")
    assert b.rows == [{"request_key": 11, "machine_id": "wc2", "entity_id": 7, "state": None}]


def test_request_of_a_failed_entity_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    machine_up(db_conn, "wc2")
    lot(db_conn, 1, "failed")
    queue(db_conn, 11, 1, "wc2")
    assert only(check_database(db_conn), "orphan_request").rows[0]["state"] == "failed"


def test_request_waiting_for_a_shut_down_machine_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    machine_up(db_conn, "wc1")  # wc2 stays Shutdown
    lot(db_conn, 1, pid=subprocess.os.getpid())
    queue(db_conn, 11, 1, "wc1")
    queue(db_conn, 12, 1, "wc2")
    b = only(check_database(db_conn), "request_on_shutdown_machine")
    assert b.rows == [{"request_key": 12, "machine_id": "wc2", "entity_id": 1}]


def test_request_still_queued_after_it_was_bound_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    machine_up(db_conn, "wc1", "wc2")
    lot(db_conn, 1, "running", pid=subprocess.os.getpid())
    reserve(db_conn, "wc1", 1, 100, 11)
    queue(db_conn, 11, 1, "wc2")
    assert only(check_database(db_conn), "satisfied_request_queued").rows == [{"request_key": 11, "entity_id": 1}]


def test_run_with_results_from_two_machines_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    db_conn.execute(
        "insert into machine_run_result (machine_run_id, machine_id, param, value) "
        "values (99, 'wc1', 'x', '1'), (99, 'wc2', 'x', '1')"
    )
    assert only(check_database(db_conn), "run_on_two_machines").rows == [
        {"machine_run_id": 99, "machines": ["wc1", "wc2"]}
    ]


@pytest.mark.parametrize("state", ["waiting_import", "imported", "waiting_machine", "running"])
def test_lot_whose_script_died_is_reported_stuck(db_conn: psycopg.Connection[Any], dead_pid: int, state: str) -> None:
    lot(db_conn, 1, state, pid=dead_pid)
    b = only(check_database(db_conn), "stuck_lot")
    assert b.rows == [{"entity_id": 1, "lot_id": 1, "state": state, "script_pid": dead_pid}]


def test_lot_past_created_that_never_had_a_script_is_reported_stuck(db_conn: psycopg.Connection[Any]) -> None:
    lot(db_conn, 1, "waiting_import")
    assert only(check_database(db_conn), "stuck_lot").rows[0]["script_pid"] is None


def test_lot_whose_script_is_on_the_bus_is_progressing(db_conn: psycopg.Connection[Any], dead_pid: int) -> None:
    lot(db_conn, 1, "waiting_import", pid=dead_pid)  # e.g. the script runs on another host
    peers = {"lot:1": Peer("lot:1", 1, frozenset({"LOT_MOVED"}), 0.0)}
    assert check_database(db_conn, peers) == []


def test_entity_waiting_for_a_machine_with_nothing_queued_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    lot(db_conn, 1, "waiting_machine", pid=subprocess.os.getpid())
    assert check_database(db_conn) == []  # just changed: its request may be on its way
    db_conn.execute("update lot_status set updated_at = now() - interval '1 minute'")
    assert only(check_database(db_conn), "waiting_without_request").rows[0]["entity_id"] == 1


def _cfg(tmp_path: Path, url: str, *modules: str) -> Config:
    return make_config(tmp_path, url, module=[{"name": m} for m in modules])


def test_machine_up_without_its_wc_on_the_bus_is_reported(
    tmp_path: Path, database_url: str, db_conn: psycopg.Connection[Any]
) -> None:
    machine_up(db_conn, "wc1")
    machine_up(db_conn, "wc2", status="Running")
    peers = {"wc:wc1": Peer("wc:wc1", 1, STARTED_WC, 0.0)}
    b = only(check_live(_cfg(tmp_path, database_url), db_conn, peers), "status_without_wc")
    assert b.rows == [{"machine_id": "wc2", "status": "Running"}]


def test_status_row_contradicting_its_wc_is_reported(
    tmp_path: Path, database_url: str, db_conn: psycopg.Connection[Any]
) -> None:
    machine_up(db_conn, "wc1")  # the table says Idle, the WC listens only for ME_START
    machine_up(db_conn, "wc3", status="Run_Shut")  # shutting down: the WC no longer serves SETUP_RUN
    peers = {
        "wc:wc1": Peer("wc:wc1", 1, IDLE_WC, 0.0),
        "wc:wc2": Peer("wc:wc2", 1, STARTED_WC, 0.0),
        "wc:wc3": Peer("wc:wc3", 1, IDLE_WC | {"START_RUN"}, 0.0),
    }
    b = only(check_live(_cfg(tmp_path, database_url), db_conn, peers), "status_contradicts_wc")
    assert b.rows == [
        {"machine_id": "wc1", "status": "Idle", "wc": "not started"},
        {"machine_id": "wc2", "status": "Shutdown", "wc": "started"},
    ]


def test_configured_server_absent_or_not_started_is_reported(
    tmp_path: Path, database_url: str, db_conn: psycopg.Connection[Any]
) -> None:
    peers = {"msched": Peer("msched", 1, STARTED_SERVER, 0.0), "ms": Peer("ms", 1, frozenset({"STARTUP"}), 0.0)}
    cfg = _cfg(tmp_path, database_url, "msched", "ms", "ls")
    b = only(check_live(cfg, db_conn, peers), "module_down")
    assert b.rows == [{"module": "ms", "state": "not started"}, {"module": "ls", "state": "absent"}]


def test_only_breaches_seen_in_both_snapshots_are_reported() -> None:
    first = [
        Breach("orphan_request", "p", [{"request_key": 1}, {"request_key": 2}]),
        Breach("stuck_lot", "p", [{"entity_id": 5}]),
    ]
    second = [Breach("orphan_request", "p", [{"request_key": 2}, {"request_key": 3}])]
    assert persistent(first, second) == [Breach("orphan_request", "p", [{"request_key": 2}])]


def test_check_cell_reports_a_breach_that_persists(
    tmp_path: Path, database_url: str, db_conn: psycopg.Connection[Any]
) -> None:
    lot(db_conn, 1, "exported")
    reserve(db_conn, "wc1", 1, 100, 10)
    db_conn.commit()
    with psycopg.connect(database_url) as conn:
        assert names(check_cell(_cfg(tmp_path, database_url), conn, None, settle=0.05)) == {"orphan_reservation"}


def test_entity_whose_machines_sit_idle_while_it_waits_for_its_run_is_reported(
    db_conn: psycopg.Connection[Any],
) -> None:
    machine_up(db_conn, "wc1", "wc2")  # e.g. the machine died mid-run and came back: that run is gone
    lot(db_conn, 1, "running", pid=subprocess.os.getpid())
    reserve(db_conn, "wc1", 1, 100, 10)
    lot(db_conn, 2, "running", pid=subprocess.os.getpid())
    reserve(db_conn, "wc2", 2, 101, 11)
    db_conn.execute("update machine_status set status = 'Running' where machine_id = 'wc2'")
    assert check_database(db_conn) == []  # just bound: its setup is on its way
    db_conn.execute("update reserved_machines set reserved_at = now() - interval '1 minute'")
    db_conn.execute("update machine_status set updated_at = now() - interval '1 minute'")
    b = only(check_database(db_conn), "run_lost")
    assert b.rows == [{"entity_id": 1, "machines": ["wc1"], "statuses": ["Idle"]}]


def test_machine_set_up_for_a_run_nobody_holds_is_reported(db_conn: psycopg.Connection[Any]) -> None:
    lot(db_conn, 1, "running", pid=subprocess.os.getpid())
    reserve(db_conn, "wc1", 1, 100, 10)
    db_conn.execute(
        "update machine_status set status = 'Setup', machine_run_id = 100, updated_at = now() where machine_id = 'wc1'"
    )
    db_conn.execute(
        "update machine_status set status = 'Setup', machine_run_id = 7, updated_at = now() where machine_id = 'wc2'"
    )
    assert check_database(db_conn) == []  # just set up: the lot's reservation may be going
    db_conn.execute("update machine_status set updated_at = now() - interval '1 minute'")
    b = only(check_database(db_conn), "setup_not_reserved")
    assert [(r["machine_id"], r["machine_run_id"]) for r in b.rows] == [("wc2", 7)]
