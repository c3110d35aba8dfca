"""The production record's pure parts and its figures: cell.toml [record] checked, planned time from a
shift calendar, and OEE over a history written by hand (docs/record.md's worked example)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc.config import Calendar, Shift, parse_record
from gwc.errors import ConfigError
from gwc.record import store
from gwc.record.calendar import is_planned, planned_intervals
from tests.conftest import make_config

DAY = datetime(2026, 11, 23, tzinfo=UTC)  # a Monday


def test_record_defaults_plan_every_hour_and_ship_a_small_reason_tree() -> None:
    rec = parse_record({}, [])
    assert rec.history and rec.keep_days == 90 and rec.calendar_of("wc1").always
    assert rec.reasons["tool change"] == ("planned", "scheduled_downtime")
    assert rec.reasons["mechanical"] == ("breakdown", "unscheduled_downtime")
    assert planned_intervals(rec.calendar_of("wc1"), DAY, DAY + timedelta(hours=3)) == [(DAY, DAY + timedelta(hours=3))]


@pytest.mark.parametrize(
    ("record", "says"),
    [
        ({"histroy": True}, "unknown key(s) histroy"),
        ({"keep_days": 0}, "record.keep_days must be a positive number"),
        ({"calendars": {"day": {"shifts": [{"days": ["mon"], "start": "6:00", "end": "25:00"}]}}}, "25:00"),
        ({"calendars": {"day": {"shifts": [{"days": ["monday"], "start": "06:00", "end": "14:00"}]}}}, "days must"),
        ({"calendar": "night"}, "record.calendar 'night' is not a calendar"),
        ({"reasons": {"x": {"e10": "productive", "reasons": ["a"]}}}, "record.reasons.x.e10 'productive'"),
        ({"reasons": {"x": {"e10": "engineering", "reasons": ["a"]}, "y": {"e10": "engineering", "reasons": ["a"]}}},
         "reason 'a' is also under x"),
        ({"ideal_cycle_s": {"dummy_recipe": -1}}, "record.ideal_cycle_s.dummy_recipe must be a positive number"),
        ({"timezone": "Mars/Olympus"}, "is not a time zone"),
    ],
)  # fmt: skip
def test_a_wrong_record_section_is_refused_naming_its_key(tmp_path: Path, record: dict[str, Any], says: str) -> None:
    with pytest.raises(ConfigError) as e:
        make_config(tmp_path, None, record=record)
    assert says in str(e.value)


def test_a_machine_naming_an_unknown_calendar_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="machine wc1: calendar 'night' is not in record.calendars"):
        make_config(tmp_path, None, machine=[{"id": "wc1", "kind": "dummy", "calendar": "night"}])


def test_shifts_give_planned_time_including_one_over_midnight() -> None:
    cal = Calendar("two", (Shift((0, 1, 2, 3, 4), 6 * 60, 14 * 60), Shift((4,), 22 * 60, 2 * 60)))
    week = planned_intervals(cal, DAY, DAY + timedelta(days=7))
    assert sum((b - a).total_seconds() for a, b in week) == 5 * 8 * 3600 + 4 * 3600
    friday_night = DAY + timedelta(days=4, hours=23)
    assert is_planned(cal, friday_night) and is_planned(cal, friday_night + timedelta(hours=3, minutes=1)) is False
    assert not is_planned(cal, DAY + timedelta(days=5, hours=10))  # Saturday
    assert planned_intervals(Calendar("never", ()), DAY, DAY + timedelta(days=7)) == []


def _minutes(m: float) -> datetime:
    return DAY + timedelta(hours=6, minutes=m)


def test_oee_of_the_worked_example_in_docs_record(db_conn: psycopg.Connection[Any], tmp_path: Path) -> None:
    """docs/record.md's example: an 8 h shift, 40 runs of 9 min (ideal 8 min), 2 failed, down 20 min for a
    tool change and 40 min for a mechanical fault, idle the rest: A 0.75, P 0.8889, Q 0.95, OEE 0.6333."""
    rec = parse_record(
        {
            "calendar": "day",
            "calendars": {"day": {"shifts": [{"days": "all", "start": "06:00", "end": "14:00"}]}},
            "ideal_cycle_s": {"dummy_recipe": 480},
        },
        [],
    )
    cur = db_conn.cursor()
    rows: list[tuple[Any, ...]] = [(_minutes(-30), "Idle", "start", None, None)]
    for k in range(40):
        rows.append((_minutes(9 * k), "Running", "run", "dummy_recipe", 1000 + k))
        rows.append((_minutes(9 * k + 9), "Idle", "run_end", None, None))
        cur.execute(
            "insert into machine_run_outcome (machine_run_id, machine_id, ack_code, ended_at) "
            "values (%s, 'wc1', %s, %s)",
            (1000 + k, "RUN_FAIL" if k in (3, 30) else "ACK_OK", _minutes(9 * k + 9) - timedelta(seconds=1)),
        )
    for start, end, reason in ((360, 380, "tool change"), (420, 460, "mechanical")):
        rows.append((_minutes(start), "Shutdown", "operator_stop", None, None))
        rows.append((_minutes(end), "Idle", "start", None, None))
        cur.execute(
            "insert into downtime_events (machine_id, started_at, ended_at, cause, reason, e10_state) "
            "values ('wc1', %s, %s, 'operator_stop', %s, %s)",
            (_minutes(start), _minutes(end), reason, rec.reasons[reason][1]),
        )
    cur.executemany(
        "insert into machine_state_history (at, machine_id, status, cause, recipe_id, machine_run_id) "
        "values (%s, 'wc1', %s, %s, %s, %s)",
        rows,
    )
    db_conn.commit()
    rep = store.oee(db_conn, rec, DAY, DAY + timedelta(days=1), ["wc1"])
    (wc1,) = rep["machines"]
    assert (wc1["planned_s"], wc1["run_s"], wc1["down_s"]) == (480 * 60, 360 * 60, 60 * 60)
    assert (wc1["parts"], wc1["good_parts"]) == (40, 38)
    assert wc1["availability"] == pytest.approx(0.75)
    assert wc1["performance"] == pytest.approx(320 / 360)
    assert wc1["quality"] == pytest.approx(0.95)
    assert wc1["oee"] == pytest.approx(0.75 * 320 / 360 * 0.95) and round(wc1["oee"], 4) == 0.6333
    assert wc1["downtime"] == [
        {"reason": "mechanical", "seconds": 2400.0, "events": 1},
        {"reason": "tool change", "seconds": 1200.0, "events": 1},
    ]
    segs = store.timeline(db_conn, rec, "wc1", DAY, DAY + timedelta(days=1))
    seconds: dict[str, float] = {}
    for s in segs:
        seconds[s.e10] = seconds.get(s.e10, 0.0) + s.seconds
    assert seconds == {
        "non_scheduled": 30 * 60 + 10 * 3600,  # 05:30-06:00 (unknown before) and 14:00-24:00
        "productive": 360 * 60,
        "scheduled_downtime": 20 * 60,
        "unscheduled_downtime": 40 * 60,
        "standby": 60 * 60,
    }


def test_pruning_keeps_the_last_state_before_the_cut_and_open_downtime(db_conn: psycopg.Connection[Any]) -> None:
    now = datetime.now(UTC)
    cur = db_conn.cursor()
    for days, status in ((40, "Idle"), (35, "Shutdown"), (1, "Idle")):
        cur.execute(
            "insert into machine_state_history (at, machine_id, status, cause) values (%s, 'wc1', %s, 'start')",
            (now - timedelta(days=days), status),
        )
    cur.execute(
        "insert into downtime_events (machine_id, started_at, ended_at, cause, e10_state) values "
        "('wc1', %(a)s, %(b)s, 'alarm', 'unscheduled_downtime'), ('wc2', %(a)s, null, 'alarm', 'unscheduled_downtime')",
        {"a": now - timedelta(days=40), "b": now - timedelta(days=39)},
    )
    for days, state in ((40, "created"), (1, "imported")):
        cur.execute(
            "insert into entity_state_history (at, entity_id, lot_id, state) values (%s, 1, 1, %s)",
            (now - timedelta(days=days), state),
        )
    cur.execute("set role gwc_ms")
    assert cur.execute("select prune_record('ms', 30)").fetchone() == (2,)  # the Idle of day 40, the closed event
    cur.execute("reset role; set role gwc_ls")
    assert cur.execute("select prune_record('ls', 30)").fetchone() == (1,)
    cur.execute("reset role")
    kept = cur.execute("select status from machine_state_history where machine_id = 'wc1' order by at").fetchall()
    assert kept == [("Shutdown",), ("Idle",)]  # the state wc1 was in when the kept time begins, and after
    assert cur.execute("select machine_id from downtime_events").fetchall() == [("wc2",)]
    with pytest.raises(psycopg.errors.InvalidParameterValue):
        cur.execute("select prune_record('cas', 30)")
    db_conn.rollback()
