"""The schema: applies twice, matches the enums' spellings, and its keys and checks refuse bad rows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import psycopg
import pytest
from psycopg import errors

from gwc import db
from gwc.config import Config
from gwc.db import schema
from gwc.errors import DatabaseError
from gwc.ipc.codes import LotState, MachineStatus

TABLES = {
    "me_config",
    "op_types",
    "machine_status",
    "accept_types",
    "recipes",
    "recipe_versions",
    "op_machine_recipe",
    "customers",
    "lot_scripts",
    "products",
    "work_orders",
    "work_order_items",
    "lots",
    "lot_entities",
    "lot_status",
    "request_machines",
    "reserved_machines",
    "machine_run_result",
    "machine_run_outcome",
    "alarm_description",
    "alarms",
    "max_values",
}


def _counts(conn: psycopg.Connection[Any]) -> dict[str, int]:
    return {t: conn.execute(f"select count(*) from {t}").fetchone()[0] for t in sorted(TABLES)}


def test_schema_applies_twice_over_an_initialised_database_without_changing_the_seed(
    cell_config: Config, db_conn: psycopg.Connection[Any]
) -> None:
    before = _counts(db_conn)
    db_conn.commit()
    db.init_schema(cell_config)
    db.init_schema(cell_config)
    assert _counts(db_conn) == before
    names = {r[0] for r in db_conn.execute("select tablename from pg_tables where schemaname = 'public'")}
    assert names >= TABLES


def test_seed_is_the_njit_cell(db_conn: psycopg.Connection[Any]) -> None:
    machines = dict(db_conn.execute("select machine_id, kind from me_config").fetchall())
    assert machines == {"cmm_wc": "cmm", "mazak": "dummy", **{f"wc{i}": "dummy" for i in range(1, 7)}}
    assert set(db_conn.execute("select distinct status from machine_status").fetchall()) == {("Shutdown",)}
    assert db_conn.execute("select count(*) from machine_status").fetchone()[0] == len(machines)
    assert db_conn.execute("select alarm_text from alarm_description where alarm_id = 'HOME_CMM'").fetchone() == (
        "Push the start button on the CMM",
    )
    # every recipe has exactly one approved version, and its checksum is the sha256 of its content
    rows = db_conn.execute(
        "select r.recipe_id, count(v.*) filter (where v.approved), "
        "bool_and(v.checksum = encode(sha256(v.content), 'hex')) "
        "from recipes r left join recipe_versions v using (recipe_id) group by 1 order by 1"
    ).fetchall()
    assert rows == [("alum_chess_set", 1, True), ("dummy_recipe", 1, True), ("mill_pawn", 1, True)]
    assert ("cmm_wc", "alum_chess_set", "alum_chess") in db_conn.execute("select * from op_machine_recipe").fetchall()
    assert db_conn.execute(
        "select script_id, lot_type from products where product_id = 'alum_chess_set'"
    ).fetchone() == ("chess", "CMM_LOT")


def test_status_and_state_checks_accept_exactly_the_enum_spellings(db_conn: psycopg.Connection[Any]) -> None:
    for status in MachineStatus:
        db_conn.execute("update machine_status set status = %s where machine_id = 'wc1'", (status.value,))
    _lot_with_entity(db_conn)
    for state in LotState:
        db_conn.execute("update lot_status set state = %s where entity_id = 1", (state.value,))
    db_conn.commit()


def test_init_schema_registers_machines_of_the_config_the_seed_does_not_know(
    tmp_path: Any, database_url: str, db_conn: psycopg.Connection[Any]
) -> None:
    from tests.conftest import make_config

    cfg = make_config(tmp_path, database_url, machine=[{"id": "wc9", "kind": "dummy", "liveness": 1.5}])
    db.init_schema(cfg)
    assert db_conn.execute("select kind, liveness_s from me_config where machine_id = 'wc9'").fetchone() == (
        "dummy",
        1.5,
    )
    assert db_conn.execute("select status from machine_status where machine_id = 'wc9'").fetchone() == ("Shutdown",)
    assert ("dummy_recipe", "dummy_op") in db_conn.execute(
        "select recipe_id, op_type from op_machine_recipe where machine_id = 'wc9'"
    ).fetchall()


def _lot_with_entity(conn: psycopg.Connection[Any]) -> None:
    conn.execute("insert into lots (lot_id, product_id, quantity, script_id) values (1, 'alum_chess_set', 1, 'chess')")
    conn.execute("insert into lot_entities (entity_id, lot_id, unit) values (1, 1, 1)")
    conn.execute("insert into lot_status (entity_id, lot_id, state) values (1, 1, 'created')")


BAD_ROWS = {
    "request_for_unknown_machine": (
        "insert into request_machines (request_key, entity_id, machine_id, op_type) values (1, 1, 'nope', 'measure')",
        errors.ForeignKeyViolation,
    ),
    "request_for_unknown_entity": (
        "insert into request_machines (request_key, entity_id, machine_id, op_type) values (1, 99, 'wc1', 'measure')",
        errors.ForeignKeyViolation,
    ),
    "request_for_unknown_op_type": (
        "insert into request_machines (request_key, entity_id, machine_id, op_type) values (1, 1, 'wc1', 'juggle')",
        errors.ForeignKeyViolation,
    ),
    "machine_status_outside_the_set": (
        "update machine_status set status = 'Broken' where machine_id = 'wc1'",
        errors.CheckViolation,
    ),
    "status_spelled_in_lowercase": (
        "update machine_status set status = 'idle' where machine_id = 'wc1'",
        errors.CheckViolation,
    ),
    "machine_reserved_twice": (
        "insert into reserved_machines (machine_id, entity_id, machine_run_id, request_key) "
        "values ('wc1', 1, 10, 1), ('wc1', 1, 11, 2)",
        errors.UniqueViolation,
    ),
    "reservation_for_unknown_entity": (
        "insert into reserved_machines (machine_id, entity_id, machine_run_id, request_key) values ('wc1', 42, 1, 1)",
        errors.ForeignKeyViolation,
    ),
    "negative_order_quantity": (
        "insert into work_orders (work_order_id, customer_id) values (1, 'NJIT'); "
        "insert into work_order_items values (1, 'milled_pawn', -3)",
        errors.CheckViolation,
    ),
    "lot_of_zero": ("insert into lots (lot_id, quantity) values (2, 0)", errors.CheckViolation),
    "cleared_alarm_without_cleared_by": (
        "insert into alarms (alarm_no, alarm_id, known, alarm_text, raised_by, cleared_at) "
        "values (1, 'HOME_CMM', true, 'x', 'wc:cmm_wc', now())",
        errors.CheckViolation,
    ),
    "known_alarm_without_alarm_id": (
        "insert into alarms (alarm_no, known, alarm_text, raised_by) values (1, true, 'x', 'cas')",
        errors.CheckViolation,
    ),
    "lot_state_outside_the_set": ("update lot_status set state = 'lost' where entity_id = 1", errors.CheckViolation),
    "lot_status_naming_another_lot_than_its_entity": (
        "insert into lots (lot_id) values (2); update lot_status set lot_id = 2 where entity_id = 1",
        errors.ForeignKeyViolation,
    ),
    "second_approved_recipe_version": (
        "insert into recipe_versions (recipe_id, version, content, checksum, approved) "
        "values ('mill_pawn', 2, 'x', encode(sha256('x'), 'hex'), true)",
        errors.UniqueViolation,
    ),
    "checksum_not_sha256_hex": (
        "insert into recipe_versions (recipe_id, version, content, checksum) values ('mill_pawn', 2, 'x', 'abc')",
        errors.CheckViolation,
    ),
    "machine_of_unknown_kind": (
        "insert into me_config (machine_id, kind) values ('r2', 'robot')",
        errors.CheckViolation,
    ),
    "accept_type_unknown": ("insert into accept_types values ('wc1', 'juggle')", errors.ForeignKeyViolation),
    "alarm_severity_unknown": ("insert into alarm_description values ('X', 'x', 'fatal')", errors.CheckViolation),
    "run_result_param_twice": (
        "insert into machine_run_result (machine_run_id, machine_id, param, value) "
        "values (1, 'wc1', 'RCP_STATUS', 'PASS'), (1, 'wc1', 'RCP_STATUS', 'FAIL')",
        errors.UniqueViolation,
    ),
    "status_for_unconfigured_machine": (
        "insert into machine_status (machine_id, status) values ('ghost', 'Idle')",
        errors.ForeignKeyViolation,
    ),
    "entity_its_own_parent": (
        "insert into lot_entities (entity_id, lot_id, parent_entity_id) values (5, 1, 5)",
        errors.CheckViolation,
    ),
}


def test_constraints_refuse_bad_rows(db_conn: psycopg.Connection[Any]) -> None:
    """One fresh database, each bad row tried in its own savepoint: every one must be refused."""
    _lot_with_entity(db_conn)
    accepted = []
    for name, (statement, error) in BAD_ROWS.items():
        try:
            with db_conn.transaction():
                db_conn.execute(statement)
            accepted.append(name)
        except error:
            pass
    assert accepted == []


def test_the_good_rows_next_to_the_bad_ones_are_accepted(db_conn: psycopg.Connection[Any]) -> None:
    _lot_with_entity(db_conn)
    db_conn.execute(
        "insert into request_machines (request_key, entity_id, machine_id, op_type) "
        "values (1, 1, 'wc1', 'mill_chess'), (1, 1, 'cmm_wc', 'alum_chess')"
    )
    db_conn.execute(
        "insert into reserved_machines (machine_id, entity_id, machine_run_id, request_key) values ('wc1', 1, 10, 1)"
    )
    db_conn.execute(
        "insert into alarms (alarm_no, alarm_id, known, machine_id, alarm_text, raised_by) "
        "values (1, 'NOT_IN_TABLE', false, 'cmm_wc', 'odd', 'wc:cmm_wc')"
    )
    db_conn.execute("update alarms set cleared_by = 'hi', cleared_at = now() where alarm_no = 1")
    db_conn.execute(
        "insert into recipe_versions (recipe_id, version, content, checksum) "
        "values ('mill_pawn', 2, 'x', encode(sha256('x'), 'hex'))"
    )
    seqs = [r[0] for r in db_conn.execute("select seq from request_machines order by seq")]
    assert len(seqs) == 2 and seqs[0] < seqs[1]
    db_conn.commit()


def test_a_schema_application_that_ends_in_a_deadlock_is_applied_again(
    cell_config: Config, db_conn: psycopg.Connection[Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`gwc db start` while the cell runs: the DDL's locks may deadlock with a module's reads; the server
    undoes the whole transaction, and init_schema applies it again. A sequence (which no rollback undoes)
    makes the last file's first application fail as a deadlock would, the second pass."""
    db_conn.execute("create sequence if not exists test_schema_tries")
    db_conn.commit()
    once = tmp_path / "999_deadlock_once.sql"
    once.write_text(
        "DO $$ BEGIN IF nextval('test_schema_tries') = 1 THEN "
        "RAISE EXCEPTION 'deadlock detected (test)' USING ERRCODE = '40P01'; END IF; END $$;"
    )
    monkeypatch.setattr(schema, "sql_files", lambda: [*sorted(schema.SQL_DIR.glob("*.sql")), once])
    monkeypatch.setattr(schema, "SCHEMA_PAUSE_S", 0.0)
    db.init_schema(cell_config)
    assert db_conn.execute("select last_value from test_schema_tries").fetchone()[0] == 2
    db_conn.execute("alter sequence test_schema_tries restart")  # every try a deadlock now: refused, said so
    db_conn.commit()
    once.write_text("DO $$ BEGIN RAISE EXCEPTION 'deadlock detected (test)' USING ERRCODE = '40P01'; END $$;")
    with pytest.raises(DatabaseError, match=r"failed 3 times: deadlock detected \(test\)"):
        db.init_schema(cell_config)
