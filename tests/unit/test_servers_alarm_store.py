"""The Cell Alarm Server's store (gwc/servers/alarm_store.py) and the Status Line Server's
(gwc/servers/status_line_store.py) on the template database, without a bus: an alarm recorded known
or not, numbered, with its description's actions; a description added and changed; a clearing done
once (Refused after); and what the status line reads of them."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.errors import Refused
from gwc.ipc.codes import AckCode
from gwc.servers import alarm_store, status_line_store

T = TypeVar("T")


@pytest.fixture
def cas(cell_config: Config) -> Iterator[psycopg.Connection[Any]]:
    """The Cell Alarm Server's own connection (role gwc_cas)."""
    with db.connect(cell_config, role="cas") as c:
        yield c


@pytest.fixture
def sls(cell_config: Config) -> Iterator[psycopg.Connection[Any]]:
    """The Status Line Server's own connection (role gwc_sls: reads only)."""
    with db.connect(cell_config, role="sls") as c:
        yield c


def step(conn: psycopg.Connection[Any], fn: Callable[[Any], T]) -> T:
    return db.transaction(conn, fn)


def test_an_alarm_is_recorded_known_or_not_with_its_descriptions_actions(cas: psycopg.Connection[Any]) -> None:
    before = step(cas, alarm_store.pending())
    step(cas, alarm_store.describe("TEST_SHUT", "test shutdown", "error", ["shutdown", "page"]))
    known = step(cas, lambda cur: alarm_store.record(cur, "TEST_SHUT", None, "wc1", "test"))
    assert known.known and known.text == "test shutdown" and known.actions == ("shutdown", "page")
    odd = step(cas, lambda cur: alarm_store.record(cur, "NO_SUCH", None, None, "test"))
    assert not odd.known and odd.text == "unknown alarm NO_SUCH" and odd.actions == ()
    assert odd.alarm_no > known.alarm_no and step(cas, alarm_store.pending()) == before + 2
    step(cas, alarm_store.actions_taken(known.alarm_no, "machine wc1 shut down"))
    taken = cas.execute("select actions_taken from alarms where alarm_no = %s", (known.alarm_no,)).fetchone()
    assert taken == ("machine wc1 shut down",)


def test_a_description_changes_only_what_is_given(cas: psycopg.Connection[Any]) -> None:
    first = step(cas, alarm_store.describe("TEST_X", None, None, None))
    assert first == alarm_store.Described("TEST_X", "warning", ())
    again = step(cas, alarm_store.describe("TEST_X", "text", None, ["page"]))
    assert again == alarm_store.Described("text", "warning", ("page",))


def test_an_alarm_is_cleared_once_and_an_unknown_one_is_refused(cas: psycopg.Connection[Any]) -> None:
    no = step(cas, lambda cur: alarm_store.record(cur, "HOME_CMM", None, "cmm_wc", "test")).alarm_no
    assert step(cas, lambda cur: alarm_store.clear(cur, no, "op")) == alarm_store.Cleared("HOME_CMM", "cmm_wc")
    for alarm_no, code, why in ((no, AckCode.NOTNOW, "already cleared by op"), (99_999, AckCode.UNKNOWN, "no alarm")):
        with pytest.raises(Refused) as refused:
            step(cas, lambda cur, n=alarm_no: alarm_store.clear(cur, n, "op"))
        assert refused.value.ack_code == code and why in refused.value.detail


def test_the_status_line_reads_pending_alarms_and_the_newest(
    cas: psycopg.Connection[Any], sls: psycopg.Connection[Any]
) -> None:
    quiet = step(sls, status_line_store.waiting)
    made = step(cas, lambda cur: alarm_store.record(cur, "NO_SUCH", "odd", None, "test"))
    now = step(sls, status_line_store.waiting)
    assert now.alarms == quiet.alarms + 1
    assert now.newest == status_line_store.Alarm(made.alarm_no, "odd", False)
    assert now.imports == quiet.imports and now.exports == quiet.exports
