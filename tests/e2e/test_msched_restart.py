"""MSCHED killed with kill -9 and started again: nothing lost, nothing bound twice (issue 5, item 6)."""

from __future__ import annotations

from typing import Any

from gwc.ipc.codes import AckCode
from tests.e2e.test_msched import (
    T,
    add_entities,
    machines_up,
    msched_cell,
    queued_keys,
    request,
    reservations,
    unreserve,
    wait_queued,
)
from tests.harness import CellHarness, wait_for


def kill9_and_restart(cell: CellHarness, *extra: str) -> None:
    """kill -9 MSCHED and start it again; return once the NEW one is started (the old hello may linger)."""
    old = cell.bus.peers()["msched"].inc
    cell.kill("msched")
    cell.start("msched", extra_args=extra)

    def new_one_started() -> bool:
        peer = cell.bus.peers().get("msched")
        return peer is not None and peer.inc != old and "SHUTDOWN" in peer.interest

    wait_for(new_one_started, T, "the restarted msched to be started")


def test_kill9_with_requests_queued_and_machines_reserved_loses_nothing(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2, 3, 4, 5, 6)
    machines_up(cell, "wc1", "wc2", "wc3")
    request(cell, 1, "wc1").comp()
    request(cell, 2, "wc2").comp()
    three = request(cell, 3, "wc1")
    four_a, four_b = request(cell, 4, "wc1"), request(cell, 4, "wc2")  # wc1 OR wc2
    five = request(cell, 5, "wc2")
    in_flight = request(cell, 6, "wc3")
    first = in_flight.comp(acknowledge=False)  # bound and told, but MSCHED dies before the ack
    assert first.ack_code == AckCode.ACK_OK
    wait_queued(cell, 4)
    before = reservations(cell)

    kill9_and_restart(cell)

    # The answer that was not acknowledged comes again, the same one: bound once, not twice.
    again = in_flight.comp()
    assert (again.ack_code, again.request_key, again.machine_run_id) == (
        AckCode.ACK_OK,
        in_flight.key,
        first.machine_run_id,
    )
    assert reservations(cell) == before == {"wc1": 1, "wc2": 2, "wc3": 6}
    assert queued_keys(cell) == sorted([three.key, four_a.key, four_b.key, five.key])

    # Every waiting lot is served, in its own conversation, FIFO.
    assert unreserve(cell, 1).ack_code == AckCode.ACK_OK
    assert three.comp().ack_code == AckCode.ACK_OK and three.reserved == ["wc1"]
    assert unreserve(cell, 2).ack_code == AckCode.ACK_OK
    assert four_b.comp().ack_code == AckCode.ACK_OK and four_b.reserved == ["wc2"]
    assert four_a.comp().ack_code == AckCode.REQ_CANCEL
    assert unreserve(cell, 4).ack_code == AckCode.ACK_OK
    assert five.comp().ack_code == AckCode.ACK_OK
    assert reservations(cell) == {"wc1": 3, "wc2": 5, "wc3": 6}
    assert queued_keys(cell) == []
    run_ids = cell.query("select machine_run_id from reserved_machines")
    assert len(run_ids) == len(set(run_ids))
    wait_for(lambda: cell.query("select count(*) from request_outcomes")[0][0] == 0, T, "every answer acknowledged")


def test_clean_start_wipes_the_queue_as_the_thesis_did(make_cell: Any) -> None:
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1")
    request(cell, 1, "wc1").comp()
    waiting = request(cell, 2, "wc1")
    wait_queued(cell, 1)
    kill9_and_restart(cell, "--clean")
    assert queued_keys(cell) == [] and reservations(cell) == {}
    assert cell.log_has("msched", "--clean")
    # wc1 is free again for whoever asks now.
    waiting.conv.end()
    again = request(cell, 2, "wc1")
    assert again.comp().ack_code == AckCode.ACK_OK


def test_satisfied_alternative_group_survives_kill9(make_cell: Any) -> None:
    """The bound alternative groups live in the database: after a kill -9, a late alternative of a
    served group is still refused REQ_CANCEL, even once its machine was given back."""
    cell = msched_cell(make_cell)
    cell.start("msched")
    add_entities(cell, 1, 2)
    machines_up(cell, "wc1", "wc2")
    request(cell, 2, "wc2").comp()
    first = request(cell, 1, "wc1", alt_group="step1")
    assert first.comp().ack_code == AckCode.ACK_OK
    assert unreserve(cell, 1).ack_code == AckCode.ACK_OK
    wait_for(lambda: cell.query("select count(*) from request_outcomes")[0][0] == 0, T, "the answer acknowledged")

    kill9_and_restart(cell)

    late = request(cell, 1, "wc1", alt_group="step1")
    assert (late.ack.ack_code, late.ack.note) == (AckCode.REQ_CANCEL, f"alternative {first.key} already satisfied")
    assert queued_keys(cell) == [] and reservations(cell) == {"wc2": 2}
    assert request(cell, 1, "wc1").comp().ack_code == AckCode.ACK_OK  # without alt_group: queued and bound
    assert reservations(cell) == {"wc1": 1, "wc2": 2}
