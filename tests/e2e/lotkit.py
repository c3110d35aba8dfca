"""What the lot tests share: a cell with servers and machines up, the operator's `gwc` commands, the
CMM's start button, and looks at the lots' tables and travellers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc.cell import startup
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.lot.entity import read_traveller
from tests.harness import CellHarness, wait_for

# A lot script of two runs of the dummy operation, each on whichever dummy machine is free.
TWO_DUMMY_RUNS = '''"""Two runs of the dummy operation, on whichever dummy machine is free."""

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    for _ in range(2):
        entity.operate("dummy_op")
    entity.lot_completed("PASS")
    entity.wait_for_export()
'''


def default_machines(run_time: float = 0.2, measure_time: float = 0.2) -> list[dict[str, Any]]:
    """The default test machines: wc1, wc2 (dummy mills) and cmm_wc (the CMM simulator, every part PASS)."""
    return [
        {"id": "wc1", "kind": "dummy", "run_time": run_time},
        {"id": "wc2", "kind": "dummy", "run_time": run_time},
        {
            "id": "cmm_wc",
            "kind": "cmm",
            "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0},
            "sim": {"measure_time": measure_time, "pattern": "P"},
        },
    ]


def gwc(cell: CellHarness, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """Run a `gwc` command against this cell, as the operator would."""
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=cell.env(), capture_output=True, text=True, timeout=timeout
    )


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, f"{result.args}: exit {result.returncode}: {result.stderr}{result.stdout}"
    assert "Traceback" not in result.stderr
    return result.stdout


def clear_homing_alarms(cell: CellHarness, machine_id: str) -> int:
    """Push the CMM's start button: clear its pending HOME_CMM alarms. Returns how many."""
    n = 0
    for (alarm_no,) in cell.query(
        "SELECT alarm_no FROM alarms WHERE cleared_at IS NULL AND machine_id = %s AND alarm_id = 'HOME_CMM'", machine_id
    ):
        conv, batch = cell.bus.request(
            "ALARM_CLR_REQ", message("Alarm_Clear_Request", alarm_no=alarm_no, cleared_by="test operator"), to="cas"
        )
        conv.end()
        assert batch.first.ack_code == AckCode.ACK_OK
        n += 1
    return n


def start_machine(cell: CellHarness, machine_id: str) -> None:
    """ME_START a machine whose processes run, pushing the CMM's start button when it asks."""
    outcome: dict[str, Any] = {}

    def go() -> None:
        try:
            outcome["ok"] = startup(cell.bus, f"wc:{machine_id}", "ME_START", timeout=30)
        except Exception as e:  # reported by the caller
            outcome["error"] = e

    t = threading.Thread(target=go)
    t.start()
    while t.is_alive():
        clear_homing_alarms(cell, machine_id)
        t.join(0.1)
    assert "error" not in outcome, outcome.get("error")


def cell_with_machines(cell: CellHarness, *machines: str) -> CellHarness:
    """Start every server, and the machines named (processes, then ME_START)."""
    cell.start_servers()
    for m in cell.cfg.machines:
        cell.start_machine_processes(m.id)
    for m in machines:
        start_machine(cell, m)
    return cell


def order(cell: CellHarness, *items: str) -> list[int]:
    """`gwc order new --customer NJIT ITEMS`: the entity ids, in lot order."""
    made = json.loads(ok(gwc(cell, "order", "new", "--customer", "NJIT", *items, "--json")))
    return [e for lot in made["lots"] for e in lot["entities"]]


def state(cell: CellHarness, entity: int) -> tuple[str, str | None]:
    rows = cell.query("SELECT state, reason FROM lot_status WHERE entity_id = %s", entity)
    return (rows[0][0], rows[0][1]) if rows else ("none", None)


def wait_state(cell: CellHarness, entity: int, *states: str, timeout: float = 20) -> str:
    """Wait for the entity to reach one of `states`; fail at once if it fails unexpectedly."""

    def reached() -> str | None:
        st, reason = state(cell, entity)
        if st == "failed" and "failed" not in states:
            raise AssertionError(f"entity {entity} failed: {reason}\n{lot_log(cell, entity)[-3000:]}")
        return st if st in states else None

    return wait_for(reached, timeout, f"entity {entity} to be {' or '.join(states)}")


def import_export_all(cell: CellHarness, entities: list[int], timeout: float = 40) -> None:
    """Be the operator: import each entity that waits for it, export each finished one, until all are out."""

    def step() -> bool:
        states = {e: state(cell, e)[0] for e in entities}
        failed = [e for e, s in states.items() if s == "failed"]
        assert not failed, f"entities failed: {[(e, state(cell, e)[1]) for e in failed]}"
        if "waiting_import" in states.values():
            ok(gwc(cell, "import", "--all"))
        if "waiting_export" in states.values():
            ok(gwc(cell, "export", "--all"))
        return all(s == "exported" for s in states.values())

    wait_for(step, timeout, f"entities {entities} to be exported", interval=0.2)


def lot_log(cell: CellHarness, entity: int) -> str:
    return cell.log_text(f"lot:{entity}")


def script_pid(cell: CellHarness, entity: int) -> int | None:
    rows = cell.query("SELECT script_pid FROM lot_status WHERE entity_id = %s", entity)
    return rows[0][0] if rows else None


def steps(cell: CellHarness, entity: int) -> list[dict[str, Any]]:
    return (read_traveller(cell.cfg, entity) or {}).get("steps", [])


def holdings(cell: CellHarness, entity: int) -> tuple[int, int]:
    """(requests queued, machines reserved) of an entity."""
    q = cell.query("SELECT count(*) FROM request_machines WHERE entity_id = %s", entity)[0][0]
    r = cell.query("SELECT count(*) FROM reserved_machines WHERE entity_id = %s", entity)[0][0]
    return int(q), int(r)


def stop_lot_scripts(cell: CellHarness) -> None:
    """Kill whatever lot script a failing test left (they are detached from the harness)."""
    for path in Path(cell.cfg.run_dir).glob("lot-*.pid"):
        try:
            pid = int(json.loads(path.read_text())["pid"])
            os.killpg(pid, signal.SIGKILL)
        except (OSError, ValueError, KeyError):
            pass


@pytest.fixture
def lot_cell(make_cell: Any) -> Iterator[Any]:
    """make_cell, and every lot script a test started is killed at its end, even when it fails."""
    cells: list[CellHarness] = []

    def make(**config: Any) -> CellHarness:
        c = make_cell(**config)
        cells.append(c)
        return c

    yield make
    for c in cells:
        stop_lot_scripts(c)
