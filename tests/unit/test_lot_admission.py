"""The order book's budget (gwc/budget.py) and queue (gwc/lot/admission.py): what the cell plans for
its database connections, the lot scripts' role held to its share, and the queue of scripts that wait
for a place. The agent's use of both runs end to end in tests/e2e/test_order_book.py."""

from __future__ import annotations

import dataclasses
import logging
import threading
from pathlib import Path
from typing import Any

import pytest

from gwc import db
from gwc.budget import MIN_RUNNING, OPERATOR_RESERVE, SUPERUSER_RESERVED, plan
from gwc.db.schema import limit_lot_connections
from gwc.errors import ConfigError, DatabaseUnavailable
from gwc.lot.admission import LotQueue
from gwc.lot.core import OVER_BUDGET, LotReads
from gwc.lot.state import EntityState
from tests.conftest import PgCluster, make_config
from tests.harness import wait_for

LOG = logging.getLogger("test")


def machines(n: int) -> list[dict[str, Any]]:
    return [{"id": f"m{i}", "kind": "dummy"} for i in range(n)]


def test_the_budget_gives_modules_and_operator_theirs_and_lot_scripts_the_rest(tmp_path: Path) -> None:
    cfg = make_config(tmp_path, None, module=[{"name": m} for m in ("cas", "ls", "msched")], machine=machines(5))
    budget = plan(cfg)
    assert budget.max_connections == 200 and budget.modules == 3 + 5 and budget.operator == OPERATOR_RESERVE
    assert budget.lots == 200 - SUPERUSER_RESERVED - OPERATOR_RESERVE - 8
    assert budget.running == 4 * 5, "four lot scripts a machine by default"
    assert plan(make_config(tmp_path, None, machine=machines(1))).running == MIN_RUNNING


def test_the_budget_obeys_max_running_and_never_exceeds_the_lots_share(tmp_path: Path) -> None:
    assert plan(make_config(tmp_path, None, machine=machines(5), lots={"max_running": 3})).running == 3
    small = make_config(tmp_path, None, machine=machines(5), database={"settings": {"max_connections": 40}})
    assert plan(small).lots == 40 - SUPERUSER_RESERVED - OPERATOR_RESERVE - 5
    assert plan(small).running == plan(small).lots, "never more scripts than connections for them"


@pytest.mark.parametrize(
    ("sections", "says"),
    [
        ({"lots": {"max_running": -1}}, "lots.max_running"),
        ({"lots": {"max_running": "many"}}, "lots.max_running"),
        ({"database": {"settings": {"max_connections": 25}}, "machine": machines(10)}, "leave none for lot scripts"),
        ({"database": {"settings": {"max_connections": 5}}}, "at least 10"),
    ],
)
def test_a_budget_that_cannot_work_is_refused_with_what_to_change(
    tmp_path: Path, sections: dict[str, Any], says: str
) -> None:
    with pytest.raises(ConfigError, match=says):
        plan(make_config(tmp_path, None, **sections))


def test_an_external_database_is_planned_from_its_declared_limit(tmp_path: Path) -> None:
    url = "postgresql://gwc@db.plant/gwc"
    assert plan(make_config(tmp_path, url)).max_connections == 100, "PostgreSQL's default"
    declared = make_config(tmp_path, url, database={"url": url, "max_connections": 500})
    assert plan(declared).max_connections == 500


def test_the_queue_keeps_entities_in_order_once_each_and_survives_a_new_reader(tmp_path: Path) -> None:
    queue = LotQueue(tmp_path / "run")
    assert queue.pending() == [], "no folder yet: nothing queued"
    for e in (12, 3, 7):
        assert queue.add(e)
    assert not queue.add(7), "queued once"
    (tmp_path / "run" / "lot-9.pid").write_text("{}")  # not a queue entry
    (tmp_path / "run" / "lot-x.queued").write_text("")
    assert LotQueue(tmp_path / "run").pending() == [3, 7, 12], "oldest entity first, read anew from the folder"
    queue.remove(7)
    queue.remove(7)  # twice is harmless
    assert 7 not in queue and 3 in queue
    assert queue.pending() == [3, 12]


def test_a_queue_marker_is_never_created_through_a_planted_link(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    target = tmp_path / "victim"
    target.write_text("keep me")
    (run / "lot-5.queued").symlink_to(target)
    assert not LotQueue(run).add(5), "the name is taken: not created, not followed"
    assert target.read_text() == "keep me"


@pytest.fixture
def lot_limit(pg_cluster: PgCluster) -> Any:
    """gwc_lot logging in with a connection limit of 2 on the session's own cluster; lifted afterwards."""
    cfg = dataclasses.replace(
        pg_cluster.cfg, raw={**pg_cluster.cfg.raw, "database": {"settings": {"max_connections": 25}}}
    )
    assert plan(cfg).lots == 2
    with pg_cluster.admin() as conn, conn.cursor() as cur:
        limit_lot_connections(cur, cfg, LOG)
    yield cfg
    with pg_cluster.admin() as conn:
        conn.execute("alter role gwc_lot nologin connection limit -1")


def test_lot_scripts_log_in_as_their_role_and_are_held_to_its_share(lot_limit: Any) -> None:
    cfg = lot_limit
    assert db.database_url(cfg, "lot").startswith("postgresql://gwc_lot@/"), "not the superuser"
    assert db.database_url(cfg, "ms").startswith("postgresql://gwc@/"), "modules as before"
    held = [db.connect(cfg, role="lot", attempts=1) for _ in range(2)]
    try:
        assert held[0].execute("select session_user").fetchone() == ("gwc_lot",)
        with pytest.raises(DatabaseUnavailable, match=OVER_BUDGET):
            db.connect(cfg, role="lot", attempts=1)
        db.connect(cfg, role="ms", attempts=1).close()  # a module still gets its connection
    finally:
        for c in held:
            c.close()


def test_a_lot_whose_role_has_no_connection_left_waits_for_one_and_does_not_fail(
    lot_limit: Any, caplog: pytest.LogCaptureFixture
) -> None:
    cfg = lot_limit
    held = [db.connect(cfg, role="lot", attempts=1) for _ in range(2)]
    reads = LotReads(EntityState(cfg, 1, LOG))
    got: dict[str, Any] = {}

    def read() -> None:
        try:
            got["rows"] = reads.query("select 1", within=0)
        except Exception as e:  # the test reports it
            got["error"] = e

    caplog.set_level(logging.WARNING, logger="test")
    t = threading.Thread(target=read)
    t.start()
    try:
        wait_for(lambda: "hold every connection" in caplog.text or got, 10, "the lot to say it waits")
        assert t.is_alive() and not got, f"the read gave up: {got}"
    finally:
        held.pop().close()
    t.join(10)
    for c in held:
        c.close()
    reads.release()
    assert got == {"rows": [(1,)]}
