"""The HI's order screens' fields, on a real cell: Customer Entry's address (Fig. 6.2, 6.3), Work Order
Entry's date due (Fig. 6.3) and Work Order Status's due time (Fig. 6.6)."""

from __future__ import annotations

import json
from typing import Any

import pytest

from tests.e2e.lotkit import gwc, ok


@pytest.mark.soak  # ~45 s at load 10: nine `gwc` commands (suite budget)
def test_a_customer_has_an_address_and_an_order_a_due_time_shown_late_when_past(make_cell: Any) -> None:
    cell = make_cell(machines=[])
    cell.start_servers("ls")
    address = ["--address", "10 Wilber Street", "--city", "Belleville", "--state", "NJ", "--zip", "07109"]
    ok(gwc(cell, "customer", "add", "RM", "--name", "Richard Meyer", *address))
    ok(gwc(cell, "customer", "add", "RM", "--city", "Newark"))  # a field changed, the rest kept
    (rm,) = [c for c in json.loads(ok(gwc(cell, "customer", "list", "--json"))) if c["customer"] == "RM"]
    assert rm == {
        "customer": "RM",
        "name": "Richard Meyer",
        "address": "10 Wilber Street",
        "city": "Newark",
        "state": "NJ",
        "zip": "07109",
    }

    late = json.loads(
        ok(
            gwc(
                cell,
                "order",
                "new",
                "-c",
                "RM",
                "--due",
                "2020-01-15 16:54",
                "--no-scripts",
                "alum_chess_set=1",
                "--json",
            )
        )
    )
    soon = json.loads(
        ok(gwc(cell, "order", "new", "-c", "RM", "--due", "+3d", "--no-scripts", "alum_chess_set=1", "--json"))
    )
    orders = {o["work_order"]: o for o in json.loads(ok(gwc(cell, "order", "list", "--json")))}
    was_late, on_time = orders[late["work_order_id"]], orders[soon["work_order_id"]]
    assert was_late["due"] == "2020-01-15 16:54:00" and was_late["status"] == "NEW (LATE)"
    assert on_time["due"] > was_late["due"] and on_time["status"] == "NEW"
    assert was_late["customer_name"] == "Richard Meyer"
    screen = ok(gwc(cell, "order", "list"))
    assert "DUE" in screen and "2020-01-15 16:54:00" in screen
    bad = gwc(cell, "order", "new", "-c", "RM", "--due", "tomorrow-ish", "alum_chess_set=1")
    assert bad.returncode != 0 and "bad due date 'tomorrow-ish'" in bad.stderr
