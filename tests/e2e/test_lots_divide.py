"""The Lot Server's divide, merge and destroy (1.4.4) made reachable, on a real cell: `gwc lots
divide/merge/destroy` by the operator, and a lot script dividing itself and merging its child back."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from gwc.client.orders import list_lots
from tests.e2e.lotkit import gwc, import_export_all, ok, state, wait_state

SCRIPT = '''"""Divide, then merge the part back; a stranger is not ours to merge."""

from gwc.lot import OperationEntity, StepRefused

STRANGER = 0


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    (child,) = entity.divide(1, start_scripts=False)
    try:
        entity.merge(STRANGER)
        stranger = "merged"
    except StepRefused as e:
        stranger = e.ack_code
    entity.merge(child)
    entity.lot_completed(f"PASS: divided into {child}, merged back; stranger {stranger}")
    entity.wait_for_export()
'''


def listed(cell: Any, state: str | None = None) -> dict[int, dict[str, Any]]:
    """The dispatch list as `gwc lots --json` reads it (read here: each `gwc` is a fresh interpreter)."""
    with cell.db() as conn:
        return {r["entity"]: r for r in list_lots(cell.cfg, cell.log, state=state, conn=conn)}


@pytest.mark.soak  # ~45 s at load 10: a dozen `gwc` commands and a lot (suite budget)
def test_the_operator_and_a_lot_script_divide_merge_and_destroy_entities(make_cell: Any, tmp_path: Path) -> None:
    cell = make_cell(machines=[])
    cell.start_servers()
    made = json.loads(ok(gwc(cell, "order", "new", "--customer", "NJIT", "alum_chess_set=2", "--no-scripts", "--json")))
    first, second = made["lots"][0]["entities"]

    out = ok(gwc(cell, "lots", "divide", str(first), "--quantity", "2"))
    new = [int(e) for e in out.split("new entities ")[1].split(",")]
    lots = listed(cell)
    assert [lots[e]["parent"] for e in new] == [first, first] and {lots[e]["state"] for e in new} == {"created"}
    assert "lot scripts started" not in out  # the divided entity has no script running
    assert f"entity {new[0]} merged into {first}" in ok(gwc(cell, "lots", "merge", str(first), str(new[0])))
    assert f"entity {new[1]} destroyed" in ok(gwc(cell, "lots", "destroy", str(new[1])))
    assert set(listed(cell)) == {first, second}  # merged and destroyed: out of the lists
    by_cli = json.loads(ok(gwc(cell, "lots", "--json", "--state", "created")))  # the list's options, as before
    assert {r["entity"] for r in by_cli} == {first, second}
    assert f"entity {first}: lot" in ok(gwc(cell, "lots", str(first)))

    refused = gwc(cell, "lots", "merge", str(first), str(new[1]))  # destroyed already
    assert refused.returncode != 0 and f"no entity {new[1]}" in refused.stderr
    big = gwc(cell, "lots", "divide", str(first), "--quantity", "0")
    assert big.returncode != 0 and "quantity must be 1..1000" in big.stderr

    # A lot script divides itself once imported, may not merge a stranger, merges its child back.
    (tmp_path / "split.py").write_text(SCRIPT.replace("STRANGER = 0", f"STRANGER = {second}"))
    ok(gwc(cell, "script", "register", "split", str(tmp_path / "split.py"), "--product", "split_set"))
    made = json.loads(ok(gwc(cell, "order", "new", "--customer", "NJIT", "split_set=1", "--json")))
    (lot,) = made["lots"][0]["entities"]
    wait_state(cell, lot, "waiting_import")
    import_export_all(cell, [lot], timeout=40)
    st, reason = state(cell, lot)
    child = cell.query("SELECT entity_id FROM lot_entities WHERE parent_entity_id = %s", lot)[0][0]
    assert (st, reason) == ("exported", f"PASS: divided into {child}, merged back; stranger Not_Auth")
    assert cell.query("SELECT destroyed_at IS NOT NULL FROM lot_entities WHERE entity_id = %s", child) == [(True,)]
    assert cell.query("SELECT destroyed_at FROM lot_entities WHERE entity_id = %s", second) == [(None,)]
