"""The chaos soak, end to end: a whole cell under seeded faults keeps its promises, and a failing
scenario replays.

The short soak runs with every test run (CI); the ten-minute one and the replay of a broken build
are marked `soak` and run apart (`bin/test -m soak`). Each soak brings up its own private cell
(its own var/, bus group, queues) on a fresh database, and proves it left nothing behind.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from psycopg import sql

from gwc.cell import startup
from gwc.log import open_log
from gwc.soak.driver import SoakOptions, SoakReport, action_sequence, run_soak
from tests.conftest import PgCluster

BROKEN = Path(__file__).with_name("soak_broken_lot.py")


@pytest.fixture
def fresh_database(pg_cluster: PgCluster) -> Iterator[Callable[[], str]]:
    """Another fresh cell database per call (a soak run twice needs two), all dropped afterwards."""
    made: list[str] = []

    def make() -> str:
        name = f"gwc_s_{uuid.uuid4().hex[:12]}"
        with pg_cluster.admin() as conn:
            conn.execute(
                sql.SQL("create database {} template {}").format(
                    sql.Identifier(name), sql.Identifier(pg_cluster.template)
                )
            )
        made.append(name)
        return pg_cluster.url(name)

    yield make
    with pg_cluster.admin() as conn:
        for name in made:
            conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))


def soak(var: Path, url: str, **options: object) -> SoakReport:
    log = open_log("soak", var, "note")
    return run_soak(SoakOptions(var=var, database_url=url, **options), log)  # type: ignore[arg-type]


def broken_lots(report: SoakReport) -> list[str]:
    return sorted(p.split(" (entity")[0] for p in report.lot_problems if " ran 2 times" in p)


@pytest.mark.alone  # timed against a bar: run with no other test beside it
@pytest.mark.timeout(900)
def test_short_soak_under_every_kind_of_fault_keeps_every_promise(tmp_path: Path, database_url: str) -> None:
    report = soak(tmp_path / "soak", database_url, seed=2026, minutes=1.0, action_every=(4.0, 8.0))
    assert report.clean, "\n".join(report.summary())
    assert sum(report.faults.values()) >= 5
    assert report.lots_created == report.lots_planned
    assert sum(report.states.values()) >= report.lots_planned


@pytest.mark.soak  # two soaks of their own: about 90 s, so it runs apart with the long soak
@pytest.mark.timeout(900)
def test_replay_of_a_broken_build_reproduces_its_failure(tmp_path: Path, fresh_database: Callable[[], str]) -> None:
    options = dict(
        seed=11, minutes=0.3, lot_every=1.0, action_every=(4.0, 6.0), kinds=("machine_stop",), script_path=str(BROKEN)
    )
    first = soak(tmp_path / "first", fresh_database(), **options)
    again = soak(tmp_path / "again", fresh_database(), **options)
    assert not first.clean and broken_lots(first), "\n".join(first.summary())
    assert action_sequence(tmp_path / "first" / "actions.jsonl") == action_sequence(
        tmp_path / "again" / "actions.jsonl"
    )
    assert broken_lots(again) == broken_lots(first)  # the same lots, caught the same way
    assert not first.leaks and not again.leaks


@pytest.mark.soak
@pytest.mark.timeout(3600)
def test_ten_minute_soak_run_twice_with_one_seed_is_clean_both_times(
    tmp_path: Path, fresh_database: Callable[[], str]
) -> None:
    reports = [soak(tmp_path / f"run{i}", fresh_database(), seed=5, minutes=10.0) for i in (1, 2)]
    for r in reports:
        assert r.clean, "\n".join(r.summary())
    assert action_sequence(tmp_path / "run1" / "actions.jsonl") == action_sequence(tmp_path / "run2" / "actions.jsonl")


def test_gwc_check_passes_a_live_cell_and_names_a_breach(make_cell: Callable[..., Any]) -> None:
    """The soak's judge on its own: `gwc check` against real modules on the bus, then a planted breach."""
    cell = make_cell(machines=[{"id": "wc1", "kind": "dummy", "run_time": 0.1}])
    cell.start_servers()
    cell.start_machine_processes("wc1")
    assert startup(cell.bus, "wc:wc1", "ME_START") == "started"

    def check() -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "gwc", "check", "--settle", "0.5"],
            env=cell.env(),
            capture_output=True,
            text=True,
            timeout=120,
        )

    ok = check()
    assert ok.returncode == 0 and "all invariants hold" in ok.stdout, ok.stdout + ok.stderr
    cell.kill("msched", sig=signal.SIGTERM)  # its sweep would free the planted reservation within 5 s
    with cell.db() as conn:  # an exported lot still holding wc1
        conn.execute("insert into lots (lot_id) values (900)")
        conn.execute("insert into lot_entities (entity_id, lot_id) values (900, 900)")
        conn.execute("insert into lot_status (entity_id, lot_id, state) values (900, 900, 'exported')")
        conn.execute(
            "insert into reserved_machines (machine_id, entity_id, machine_run_id, request_key) "
            "values ('wc1', 900, 900, 900)"
        )
    bad = check()
    assert bad.returncode == 1, bad.stdout + bad.stderr
    assert "BREACH orphan_reservation" in bad.stdout and "entity_id=900" in bad.stdout
