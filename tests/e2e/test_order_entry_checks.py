"""`gwc order new` checks everything before it commits (issue 40): an order the Lot Server or the tables
would refuse after it was written left an orphan order with no lots."""

from __future__ import annotations

from typing import Any

import pytest

from tests.e2e.lotkit import gwc

pytestmark = pytest.mark.e2e


def test_an_order_that_would_be_refused_is_refused_before_anything_is_written(make_cell: Any) -> None:
    cell = make_cell(machines=[])  # its database alone: the checks come before the Lot Server is asked
    before = cell.query("SELECT count(*) FROM work_orders")
    for args, says in (
        (("alum_chess_set=1001",), "a lot holds 1..1000 units"),
        (("--priority", str(2**31), "alum_chess_set=1"), "priority 2147483648 is out of range"),
        (("alum_chess_set=1", "no_such_product=1"), "unknown product 'no_such_product'"),
    ):
        r = gwc(cell, "order", "new", "--customer", "NJIT", *args)
        assert r.returncode != 0 and says in r.stderr, (args, r.stderr)
    assert cell.query("SELECT count(*) FROM work_orders") == before
    assert cell.query("SELECT count(*) FROM work_order_items") == [(0,)]
