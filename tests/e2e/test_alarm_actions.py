"""Alarms with actions (1.4.5), on a real cell: a machine that fails to home raises MESTRT_FAIL and the
operator is paged; an alarm whose description says shutdown has its machine shut down by the CAS."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from gwc.cell import startup
from gwc.errors import GwcError
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from tests.e2e.lotkit import gwc, ok, start_machine
from tests.harness import wait_for


def ask(cell: Any, cls: str, msg: Any, to: str) -> Any:
    conv, batch = cell.bus.request(cls, msg, to=to, timeout=15)
    conv.end()
    return batch.first


def alarm(cell: Any, alarm_id: str, machine: str) -> tuple[Any, ...] | None:
    """(alarm_no, alarm_text, actions_taken) of the machine's latest alarm of that id, once acted on."""
    rows = cell.query(
        "SELECT alarm_no, alarm_text, actions_taken FROM alarms WHERE alarm_id = %s AND machine_id = %s "
        "AND actions_taken IS NOT NULL ORDER BY alarm_no DESC",
        alarm_id,
        machine,
    )
    return rows[0] if rows else None


def test_a_machine_that_fails_to_home_raises_its_alarm_and_an_alarm_that_says_shutdown_shuts_its_machine(
    make_cell: Any, tmp_path: Path
) -> None:
    cell = make_cell(
        machines=[
            {"id": "wc1", "kind": "dummy", "fail_start": True},
            {"id": "wc2", "kind": "dummy", "run_time": 0.3, "fail_runs": [1]},
        ]
    )
    pages = tmp_path / "pages"
    pager = tmp_path / "page.sh"
    pager.write_text(f'#!/bin/sh\necho "$GWC_ALARM_NO $GWC_ALARM_ID $GWC_MACHINE: $1" >> {pages}\n')
    pager.chmod(0o755)
    with cell.cfg.path.open("a") as f:  # the operator's pager, as cell.toml names it
        f.write(f'\n[alarms]\npage_command = ["{pager}"]\n')
    cell.start_servers()
    for m in ("wc1", "wc2"):
        cell.start_machine_processes(m)

    # wc1 cannot home: its start is refused, and MESTRT_FAIL (page, by the shipped description) says why.
    with pytest.raises(GwcError):
        startup(cell.bus, "wc:wc1", "ME_START", timeout=30)
    no, text, taken = wait_for(lambda: alarm(cell, "MESTRT_FAIL", "wc1"), 20, "MESTRT_FAIL acted on")
    assert "wc1 refused to start" in text and "failed to home" in text
    assert taken == "paged (status line and page command)"
    assert f"{no} MESTRT_FAIL wc1: wc1 refused to start" in pages.read_text()
    assert cell.query("SELECT status FROM machine_status WHERE machine_id = 'wc1'")[0][0] == "Shutdown"

    # The operator makes a failed run shut its machine down and page.
    assert "actions shutdown,page" in ok(gwc(cell, "alarm", "describe", "RUN_FAIL", "--actions", "shutdown,page"))
    described = {r["alarm_id"]: r for r in json.loads(ok(gwc(cell, "alarm", "descriptions", "--json")))}
    assert described["RUN_FAIL"]["actions"] == "shutdown,page" and described["MESTRT_FAIL"]["actions"] == "page"
    bad = gwc(cell, "alarm", "describe", "RUN_FAIL", "--actions", "explode")
    assert bad.returncode != 0 and "unknown action(s) explode" in bad.stderr + bad.stdout

    start_machine(cell, "wc2")
    setup = message("Setup_Run", machine_id="wc2", recipe_id="dummy_recipe", op_type="dummy_op", machine_run_id=1)
    assert ask(cell, "SETUP_RUN", setup, "wc:wc2").ack_code == AckCode.ACK_OK
    assert (
        ask(cell, "START_RUN", message("Start_Run", machine_id="wc2", machine_run_id=1), "wc:wc2").ack_code == "ACK_OK"
    )
    no, _, taken = wait_for(lambda: alarm(cell, "RUN_FAIL", "wc2"), 20, "RUN_FAIL acted on")
    assert taken.startswith("machine wc2 shut") and taken.endswith("; paged (status line and page command)"), taken
    wait_for(
        lambda: cell.query("SELECT status FROM machine_status WHERE machine_id = 'wc2'")[0][0] == "Shutdown",
        20,
        "the CAS to shut wc2 down",
    )
    assert cell.log_has("cas", f"alarm {no} RUN_FAIL: machine wc2 shut")
    assert f"{no} RUN_FAIL wc2:" in pages.read_text()
    listed = json.loads(ok(gwc(cell, "alarm", "list", "--json")))
    assert any(r["alarm_no"] == no and r["actions_taken"] == taken for r in listed)
