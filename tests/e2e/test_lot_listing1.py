"""The rest of Listing 1 from a lot script, on a real cell: a recipe downloaded to its reserved machine
and uploaded back (the ERS stores the machine's edited copy as a new version), a new version proposed,
each refused Not_Auth for what the entity does not hold; and child operation entities started and
waited for (6.1)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from tests.e2e.lotkit import cell_with_machines, gwc, import_export_all, lot_log, ok, order, state, wait_state
from tests.harness import wait_for

RECIPES = '''"""Listing 1's ers_download / ers_upload, and a recipe tweak proposed."""

import time
from pathlib import Path

from gwc.lot import OperationEntity, StepRefused

EDITED = Path("EDITED_FLAG")  # the test touches it once it edited wc1's copy of the recipe


def refused(step):
    try:
        step()
    except StepRefused as e:
        return e.ack_code
    return "allowed"


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    res = entity.wait_for_machines(entity.request_machines("mill_chess", [["wc1"]]))
    entity.download_recipe("wc1", "mill_pawn")
    entity.setup_run("wc1", "mill_pawn", "mill_chess", res.machine_run_id, start=True)
    entity.wait_run_complete(res.machine_run_id, ["wc1"])
    entity.log.info("run done: waiting for the edit at the machine")
    while not EDITED.exists():
        time.sleep(0.05)
    uploaded = entity.upload_recipe("wc1", "mill_pawn")
    others = [
        refused(lambda: entity.download_recipe("wc2", "mill_pawn")),
        refused(lambda: entity.upload_recipe("wc2", "mill_pawn")),
    ]
    proposed = entity.propose_recipe("mill_pawn", "# mill_pawn, feed lowered by its lot\\nFEED 110\\n")
    entity.unreserve()
    others.append(refused(lambda: entity.propose_recipe("mill_pawn", "FEED 1\\n")))  # holds no machine now
    entity.lot_completed(f"PASS: uploaded v{uploaded}, proposed v{proposed}, others {' '.join(others)}")
    entity.wait_for_export()
'''

PARENT = '''"""Start two children and wait for them."""

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    children = entity.start_child("bare_pawn", 2)
    states = entity.wait_for_children(children, timeout=60)
    entity.lot_completed("PASS: children " + " ".join(f"{c}={s}" for c, s in sorted(states.items())))
    entity.wait_for_export()
'''

CHILD = '''"""Mill a bare pawn."""

from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    op = entity.operate("mill_chess")
    entity.lot_completed(f"PASS: milled on {op.machines[0]}")
    entity.wait_for_export()
'''


def _cell(lot_cell: Any) -> Any:
    machines = [{"id": m, "kind": "dummy", "run_time": 0.2} for m in ("wc1", "wc2")]
    return cell_with_machines(lot_cell(machines=machines), "wc1", "wc2")


def test_a_lot_script_downloads_runs_uploads_a_new_version_and_is_refused_what_it_does_not_hold(
    lot_cell: Any, tmp_path: Path
) -> None:
    cell = _cell(lot_cell)
    flag = tmp_path / "edited"
    script = tmp_path / "recipes.py"
    script.write_text(RECIPES.replace("EDITED_FLAG", str(flag)))
    ok(gwc(cell, "script", "register", "recipes", str(script), "--product", "recipe_pawn"))
    (lot,) = order(cell, "recipe_pawn=1")
    wait_state(cell, lot, "waiting_import")
    ok(gwc(cell, "import", str(lot)))
    wait_for(lambda: "waiting for the edit" in lot_log(cell, lot), 30, "the run and the lot to wait for the edit")

    # The download put the approved version on the machine; someone at the machine edits its copy.
    copy = cell.cfg.var / "me" / "wc1" / "mill_pawn"
    approved = cell.query("SELECT content FROM recipe_versions WHERE recipe_id = 'mill_pawn' AND version = 1")[0][0]
    assert copy.read_bytes() == bytes(approved)
    copy.write_text(copy.read_text() + "FEED 100  # slowed at the machine\n")
    flag.touch()
    import_export_all(cell, [lot], timeout=40)

    st, reason = state(cell, lot)
    assert (st, reason) == ("exported", "PASS: uploaded v2, proposed v3, others Not_Auth Not_Auth Not_Auth"), reason
    versions = cell.query(
        "SELECT version, convert_from(content, 'UTF8'), approved, created_by FROM recipe_versions "
        "WHERE recipe_id = 'mill_pawn' ORDER BY version"
    )
    assert [(v, a, by) for v, _, a, by in versions] == [
        (1, True, "seed"),
        (2, False, f"lot:{lot}"),
        (3, False, f"lot:{lot}"),
    ]
    assert versions[1][1] == copy.read_text() and "FEED 110" in versions[2][1]
    assert cell.log_has("wc:wc2", f"wc2 is not reserved to lot:{lot}")
    assert cell.log_has("ers", f"recipe mill_pawn is for no machine reserved to lot:{lot}")
    assert not (cell.cfg.var / "me" / "wc2" / "mill_pawn").exists()  # nothing reached the machine it did not hold


def test_a_lot_script_starts_child_entities_and_waits_for_them(lot_cell: Any, tmp_path: Path) -> None:
    cell = _cell(lot_cell)
    for name, text, product in (("parent", PARENT, "pawn_set"), ("bare_pawn", CHILD, "bare_pawn")):
        (tmp_path / f"{name}.py").write_text(text)
        ok(gwc(cell, "script", "register", name, str(tmp_path / f"{name}.py"), "--product", product))
    (parent,) = order(cell, "pawn_set=1")
    wait_state(cell, parent, "waiting_import")
    ok(gwc(cell, "import", str(parent)))

    def children() -> list[int]:
        rows = cell.query("SELECT entity_id FROM lot_entities WHERE parent_entity_id = %s ORDER BY 1", parent)
        return [r[0] for r in rows] if len(rows) == 2 else []

    kids = wait_for(children, 20, "the parent to start its two children")
    import_export_all(cell, [parent, *kids], timeout=60)

    st, reason = state(cell, parent)
    done = " ".join(rf"{k}=(completed|waiting_export|exported)" for k in kids)
    assert st == "exported" and re.fullmatch(f"PASS: children {done}", reason or ""), reason
    for k in kids:
        assert state(cell, k)[0] == "exported" and "PASS: milled on wc" in (state(cell, k)[1] or "")
    lots = {r["entity"]: r for r in json.loads(ok(gwc(cell, "lots", "--json")))}
    assert {parent, *kids} <= set(lots) and [lots[k]["parent"] for k in kids] == [parent, parent]
    assert len({lots[k]["lot"] for k in kids}) == 1 and lots[kids[0]]["lot"] != lots[parent]["lot"]
    orders = {lots[e]["work_order"] for e in (parent, *kids)}
    assert len(orders) == 1, orders  # the children belong to the parent's order
    assert f"lot {lots[kids[0]]['lot']} of 2 bare_pawn started as children" in lot_log(cell, parent)
