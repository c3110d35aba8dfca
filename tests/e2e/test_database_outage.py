"""The database goes away and comes back (issue 21): every module rides it out, nothing is lost.

The cell runs on a PostgreSQL cluster of the test's own (reached through GWC_DATABASE_URL, as an
external database is), so that its postmaster can be killed with -9 while lots run and started
again, as `gwc db start` does, with nothing else done by the operator. And a Machine Server
killed and started again keeps the machines' statuses, and runs in progress complete.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc import db
from gwc.config import Config
from tests.conftest import make_config
from tests.e2e.lotkit import (
    cell_with_machines,
    default_machines,
    gwc,
    import_export_all,
    ok,
    order,
    state,
    steps,
    stop_lot_scripts,
    wait_state,
)
from tests.harness import SERVERS, CellHarness, wait_for

pytestmark = pytest.mark.e2e

MACHINES = default_machines(run_time=1.0, measure_time=0.3)
MACHINE_IDS = [m["id"] for m in MACHINES]


@dataclasses.dataclass
class OwnCluster:
    """A cluster for one test, whose postmaster the test may kill."""

    cfg: Config

    @property
    def url(self) -> str:
        return db.database_url(self.cfg)

    def kill(self) -> None:
        """kill -9 the postmaster (its backends notice and go by themselves)."""
        pid = int((self.cfg.pg_dir / "postmaster.pid").read_text().split("\n", 1)[0])
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: not db.cluster_running(self.cfg), 10, "the postmaster to die")

    def start(self) -> None:
        """What `gwc db start` does."""
        db.cluster_start(self.cfg)


@pytest.fixture
def own_cluster() -> Iterator[OwnCluster]:
    base = Path(tempfile.mkdtemp(prefix="gwc-out-", dir="/var/tmp"))
    base.chmod(0o755)
    # Commits must survive the postmaster's death, as in a real cell (the suite's clusters turn
    # synchronous_commit off, which loses the last commits to a crash); fsync only matters to an OS crash.
    cfg = dataclasses.replace(make_config(base, None, database={"settings": {"fsync": False}}), database_url=None)
    try:
        db.cluster_start(cfg)
        db.init_schema(cfg)
        yield OwnCluster(cfg)
    finally:
        try:
            db.cluster_stop(cfg)
        finally:
            shutil.rmtree(base, ignore_errors=True)


@pytest.fixture
def outage_cell(xprocess: Any, tmp_path: Path, own_cluster: OwnCluster) -> Iterator[CellHarness]:
    """A private cell on the test's own cluster (GWC_DATABASE_URL), cleaned up whatever happens."""
    cell = CellHarness(xprocess, tmp_path / "cell", own_cluster.url, machines=MACHINES)
    try:
        yield cell
    finally:
        stop_lot_scripts(cell)
        cell.close()


def modules(cell: CellHarness) -> dict[str, int | None]:
    """The pid of every server and WC: a module that exited (or was restarted) shows as another."""
    return {n: cell.pid(n) for n in SERVERS} | {f"wc:{m}": cell.pid("wc", m) for m in MACHINE_IDS}


def outage_with_lots_running(cell: CellHarness, cluster: OwnCluster, outage: float) -> None:
    """Lots milled and measured on two mills and the CMM; the postmaster killed -9 while they run and
    started again `outage` seconds later; every lot exported, nobody but the database restarted."""
    cell_with_machines(cell, *MACHINE_IDS)
    entities = order(cell, "milled_pawn=3", "alum_chess_set=1")
    for e in entities:
        wait_state(cell, e, "waiting_import")
    ok(gwc(cell, "import", "--all"))
    wait_for(
        lambda: cell.query("SELECT count(*) FROM machine_status WHERE status = 'Running'")[0][0] >= 2,
        30,
        "lots to run on two machines",
    )
    before = modules(cell)

    cluster.kill()
    down_at = time.monotonic()
    for name in ("msched", "ms", "cas", "ls"):
        wait_for(lambda n=name: cell.log_has(n, "the cell database is away"), 10, f"{name} to notice")
    status = gwc(cell, "status")
    assert "database: external, DOWN" in status.stdout, status.stdout
    line = ok(gwc(cell, "status-line"))
    assert "DATABASE DOWN" in line, line
    # The outage lasts as long as the test says: the condition waited for is the time itself.
    wait_for(lambda: time.monotonic() - down_at >= outage, outage + 5, f"{outage:g}s of outage", interval=0.2)
    assert modules(cell) == before, "a module exited while the database was away"
    cluster.start()

    import_export_all(cell, entities, timeout=120)
    assert modules(cell) == before, "a module exited (or was restarted) over the outage"
    for e in entities:
        st, reason = state(cell, e)
        assert st == "exported" and reason.startswith("PASS"), (e, st, reason)
        assert steps(cell, e), f"entity {e} has no traveller"
    check = gwc(cell, "check", "--settle", "0.5")
    assert check.returncode == 0 and "all invariants hold" in check.stdout, check.stdout + check.stderr
    status = gwc(cell, "status")
    assert "database: external, up" in status.stdout, status.stdout


def outage_alarms(cell: CellHarness) -> list[tuple[Any, ...]]:
    return cell.query("SELECT alarm_no, alarm_text FROM alarms WHERE alarm_id = 'DB_DOWN'")


def test_postmaster_killed_for_5s_while_lots_run_no_module_exits_and_no_lot_fails(
    outage_cell: CellHarness, own_cluster: OwnCluster
) -> None:
    outage_with_lots_running(outage_cell, own_cluster, 5.0)
    assert outage_alarms(outage_cell) == [], "an outage under [database] outage_alarm_s (10 s) raised an alarm"


@pytest.mark.soak
def test_postmaster_killed_for_30s_while_lots_run_no_module_exits_and_an_alarm_is_raised(
    outage_cell: CellHarness, own_cluster: OwnCluster
) -> None:
    outage_with_lots_running(outage_cell, own_cluster, 30.0)
    ((_, text),) = wait_for(lambda: outage_alarms(outage_cell), 10, "alarm DB_DOWN")
    assert "the cell database was away for" in text, text


def test_machine_server_killed_and_restarted_keeps_statuses_and_the_run_in_progress_completes(
    lot_cell: Any,
) -> None:
    cell = cell_with_machines(
        lot_cell(machines=[m for m in default_machines(measure_time=4.0) if m["id"] != "wc2"]),
        "wc1",
        "cmm_wc",
    )
    (entity,) = order(cell, "alum_chess_set=1")
    wait_state(cell, entity, "waiting_import")
    ok(gwc(cell, "import", str(entity)))
    statuses = {"wc1": "Idle", "cmm_wc": "Running"}
    wait_for(lambda: machine_statuses(cell) == statuses, 20, f"machines {statuses}")
    cell.kill("ms")
    cell.start("ms")  # as the agent (or the operator) does: a new process, started through STARTUP
    assert machine_statuses(cell) == statuses
    import_export_all(cell, [entity], timeout=40)
    st, reason = state(cell, entity)
    assert st == "exported" and reason.startswith("PASS"), (st, reason)
    # Longer than the liveness window (3 s) since the restart: nobody was taken for dead, and no
    # `gwc machine start` was needed.
    wait_for(lambda: cell.log_has("ms", "cmm_wc: Running -> Idle"), 20, "the run's end to be recorded")
    assert machine_statuses(cell) == {"wc1": "Idle", "cmm_wc": "Idle"}
    assert cell.query("SELECT alarm_id FROM alarms WHERE alarm_id = 'WC_SILENT'") == []


def machine_statuses(cell: CellHarness) -> dict[str, str]:
    """The statuses of this cell's machines (the seed's others stay Shutdown)."""
    return dict(cell.query("SELECT machine_id, status FROM machine_status WHERE machine_id IN ('wc1', 'cmm_wc')"))
