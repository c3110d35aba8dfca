"""MSCHED's screen as Figure 6.8 has it, on a real cell: `gwc requests` filtered by lot, machine, entity
and op type with wildcards, a request's Zoom; and the operator's unreserve (6.2.4.7) of a machine held
by a lot whose script was killed and is not coming back."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

from gwc.client.requests import RequestFilter, request_tables
from tests.e2e.lotkit import cell_with_machines, gwc, ok, order, script_pid, wait_state
from tests.harness import wait_for

SCRIPT = '''"""Take machines and keep them (a lot that will crash while holding them)."""

import time

from gwc.lot import OperationEntity

PLAN = {
    "holder": ("mill_chess", [["wc1", "wc2"]]),
    "waiter": ("mill_chess", [["wc1"]]),
    "other": ("dummy_op", [["wc2"]]),
}


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    op_type, alternatives = PLAN[entity.product_id]
    res = entity.wait_for_machines(entity.request_machines(op_type, alternatives))
    entity.log.info("holding %s", " ".join(res.machines))
    time.sleep(600)
'''


def screen(cell: Any, *args: str) -> dict[str, Any]:
    """The screen as `gwc requests --json ARGS` reads it: read here, in this process, with the same
    function (each `gwc` costs a fresh interpreter; the command itself is run a few times below)."""
    fields = dict(zip(args[::2], args[1::2]))
    where = RequestFilter(*(fields.get(f"--{f}") for f in ("lot", "machine", "entity", "op")))
    with cell.db() as conn:
        queue, reserved, telling = request_tables(conn, where)
    return {"requests": queue, "reserved": reserved, "telling": telling}


def keys(cell: Any, *args: str) -> tuple[list[int], list[str]]:
    """(request keys waiting, machines reserved) as the filtered screen shows them."""
    s = screen(cell, *args)
    return [r["request_key"] for r in s["requests"]], [r["machine_id"] for r in s["reserved"]]


def test_requests_filter_by_each_field_with_wildcards_zoom_and_the_operator_unreserves_a_dead_lots_machine(
    lot_cell: Any, tmp_path: Path
) -> None:
    machines = [{"id": m, "kind": "dummy", "run_time": 0.2} for m in ("wc1", "wc2")]
    cell = cell_with_machines(lot_cell(machines=machines), "wc1", "wc2")
    (tmp_path / "hold.py").write_text(SCRIPT)
    register = ["script", "register", "hold", str(tmp_path / "hold.py")]
    ok(gwc(cell, *register, "--product", "holder", "--product", "waiter", "--product", "other"))

    (holder,) = order(cell, "holder=1")
    wait_state(cell, holder, "waiting_import")
    ok(gwc(cell, "import", str(holder)))
    wait_for(lambda: keys(cell)[1] == ["wc1", "wc2"], 20, "the holder to reserve wc1 and wc2")
    waiter, other = order(cell, "waiter=1", "other=1")
    for e in (waiter, other):
        wait_state(cell, e, "waiting_import")
        ok(gwc(cell, "import", str(e)))
    wait_for(lambda: len(keys(cell)[0]) == 2, 20, "two requests waiting")

    everything = screen(cell)
    by_entity = {r["entity_id"]: r for r in everything["requests"]}
    w, o = by_entity[waiter], by_entity[other]
    lot_of = {r["entity_id"]: r["lot_id"] for r in everything["requests"] + everything["reserved"]}
    assert keys(cell, "--machine", "wc1") == ([w["request_key"]], ["wc1"])
    assert keys(cell, "--machine", "wc?") == ([w["request_key"], o["request_key"]], ["wc1", "wc2"])
    assert keys(cell, "--op", "dummy*") == ([o["request_key"]], ["wc1", "wc2"])  # a reservation has no op type
    assert keys(cell, "--op", "mill_c?ess") == ([w["request_key"]], ["wc1", "wc2"])
    assert keys(cell, "--entity", str(holder)) == ([], ["wc1", "wc2"])
    assert keys(cell, "--entity", str(other)) == ([o["request_key"]], [])
    assert keys(cell, "--entity", "*", "--op", "dummy_op") == ([o["request_key"]], ["wc1", "wc2"])
    assert keys(cell, "--lot", str(lot_of[waiter])) == ([w["request_key"]], [])
    assert keys(cell, "--lot", "*", "--machine", "X") == ([w["request_key"], o["request_key"]], ["wc1", "wc2"])
    assert keys(cell, "--machine", "mazak") == ([], [])
    by_cli = json.loads(ok(gwc(cell, "requests", "--json", "--machine", "wc?", "--op", "dummy*")))[0]
    assert [r["request_key"] for r in by_cli["requests"]] == [o["request_key"]] and len(by_cli["reserved"]) == 2
    human = ok(gwc(cell, "requests", "--machine", "wc2"))
    assert "LOT_ID" in human and str(lot_of[other]) in human and "dummy_op" in human

    zoom = json.loads(ok(gwc(cell, "requests", "--json", "--zoom", str(o["request_key"]))))
    assert (zoom["entity_id"], zoom["lot_id"], zoom["product_id"], zoom["op_type"]) == (
        other,
        lot_of[other],
        "other",
        "dummy_op",
    )
    assert zoom["machines"] == [{"machine_id": "wc2", "status": "Idle", "machine_run_id": None}] and zoom["ahead"] == 1
    assert "machines:" in ok(gwc(cell, "requests", "--zoom", str(w["request_key"])))
    assert gwc(cell, "requests", "--zoom", "999999").returncode != 0

    # The holder's script runs: the operator may not take its machines from under it.
    refused = gwc(cell, "unreserve", "wc1")
    assert refused.returncode != 0 and f"held by entity {holder}, whose lot script runs" in refused.stderr

    # The holder's script is killed while the Lot Server is down: nobody reaps it, and nothing restarts
    # it (no agent). The operator frees wc1, and MSCHED gives it to the waiting request at once.
    cell.kill("ls")
    pid = script_pid(cell, holder)
    assert pid
    os.killpg(pid, signal.SIGKILL)
    wait_for(lambda: f"lot:{holder}" not in cell.bus.peers(), 10, "the killed script to leave the bus")
    assert f"reserved to entity {holder}" in ok(gwc(cell, "unreserve", "wc1"))
    wait_for(lambda: keys(cell, "--machine", "wc1")[0] == [], 10, "the waiting request to be bound")
    assert screen(cell, "--machine", "wc1")["reserved"][0]["entity_id"] == waiter
    assert keys(cell, "--machine", "wc2")[1] == ["wc2"]  # the other machine stays reserved: not asked
    assert cell.log_has("msched", f"entity {holder} freed wc1")
    not_held = gwc(cell, "unreserve", "mazak")
    assert not_held.returncode != 0 and "mazak is not reserved" in not_held.stderr
