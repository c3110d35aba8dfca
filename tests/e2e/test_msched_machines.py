"""The thesis's demonstration (7.2, 7.5) with real dummy machines: WC and ME processes, the Machine
Server and MSCHED. The test plays the lot entities only."""

from __future__ import annotations

from typing import Any

from gwc.cell import shutdown, startup
from gwc.ipc.codes import AckCode
from tests.e2e.test_msched import T, add_entities, queued_keys, request, reservations, unreserve, wait_queued
from tests.harness import wait_for

MACHINES = [{"id": m, "kind": "dummy", "run_time": 0.1} for m in ("wc1", "wc2", "wc3")]


def test_demonstration_with_real_dummy_machines(make_cell: Any) -> None:
    cell = make_cell(machines=MACHINES, modules=("cas", "ers", "ms", "msched"))
    cell.start_servers("cas", "ers", "ms", "msched")
    for m in ("wc1", "wc2"):
        cell.start_machine_processes(m)
        assert startup(cell.bus, f"wc:{m}", "ME_START") == "started"
        wait_for(
            lambda m=m: cell.query("select 1 from accept_types where machine_id = %s and op_type = 'dummy_op'", m),
            T,
            f"{m} to accept dummy_op",
        )
    add_entities(cell, *range(1, 9))

    # Several lots asking for the same machine are served in FIFO order.
    lots = [request(cell, e, "wc1") for e in (1, 2, 3)]
    order = []
    for lot in lots:
        assert lot.comp().ack_code == AckCode.ACK_OK
        order.append(lot.entity)
        assert unreserve(cell, lot.entity).ack_code == AckCode.ACK_OK
    assert order == [1, 2, 3]

    # wc1 and wc2 busy; entity 5 wants wc1 OR wc2, entity 7 only wc1. wc1 shuts down while they wait.
    request(cell, 4, "wc1").comp()
    request(cell, 6, "wc2").comp()
    alt_wc1, alt_wc2 = request(cell, 5, "wc1"), request(cell, 5, "wc2")
    only_wc1 = request(cell, 7, "wc1")
    wait_queued(cell, 3)
    assert shutdown(cell.bus, "wc:wc1", "ME_SHUT").startswith("shut down")
    # Entity 7 had no alternative: NO_MACHINE. Entity 5 keeps waiting for wc2, untold.
    assert only_wc1.comp().ack_code == AckCode.NO_MACHINE
    assert queued_keys(cell) == [alt_wc2.key]
    assert unreserve(cell, 6).ack_code == AckCode.ACK_OK
    assert alt_wc2.comp().ack_code == AckCode.ACK_OK and alt_wc2.reserved == ["wc2"]
    assert alt_wc1.comp().ack_code == AckCode.REQ_CANCEL
    # The shut-down machine is never scheduled again.
    assert unreserve(cell, 4).ack_code == AckCode.ACK_OK
    assert request(cell, 7, "wc1").ack.ack_code == AckCode.NO_MACHINE
    assert "wc1" not in reservations(cell) and queued_keys(cell) == []

    # A machine added while the cell runs is used.
    cell.start_machine_processes("wc3")
    assert startup(cell.bus, "wc:wc3", "ME_START") == "started"
    wait_for(
        lambda: cell.query("select 1 from accept_types where machine_id = 'wc3' and op_type = 'dummy_op'"),
        T,
        "wc3 to accept dummy_op",
    )
    new = request(cell, 8, "wc3")
    assert new.comp().ack_code == AckCode.ACK_OK and new.reserved == ["wc3"]
