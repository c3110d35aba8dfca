"""A lot hears its own machines: the machines' news (UPD_ME_ST, RUN_COMPL) about the machines bound to
it only, kept from it by the kernel otherwise (docs/protocol.md, *Subjects*). Everything real."""

from __future__ import annotations

import logging
import re
from typing import Any

from gwc.ipc import BlockingBus
from gwc.ipc.names import Conv
from tests.e2e.lotkit import cell_with_machines, default_machines, import_export_all, lot_log, order, steps
from tests.harness import CellHarness, wait_for

NEWS = (Conv.UPD_ME_ST, Conv.RUN_COMPL)
ACCOUNT = re.compile(r"machine news heard \(UPD_ME_ST, RUN_COMPL\): (.*)")


def heard(bus: BlockingBus) -> list[str]:
    """The machines whose news reached `bus`, in order (every conversation it was told of)."""
    got = []
    while (conv := bus.first_message(0.5)) is not None:
        if conv.first is not None:
            got.append(str(conv.first.first.machine_id))
        conv.end()
    return got


def account(cell: CellHarness, entity: int) -> dict[str, int]:
    """What the lot script said, as it closed, it heard of each machine."""
    found = wait_for(lambda: ACCOUNT.search(lot_log(cell, entity)), 10, f"lot:{entity}'s account of its news")
    return {m: int(n) for m, n in (part.rsplit(" ", 1) for part in found.group(1).split(", "))}


def test_a_lot_hears_the_news_of_its_own_machines_only_and_misses_none(lot_cell: Any) -> None:
    cell = cell_with_machines(lot_cell(machines=default_machines()), "wc1", "wc2", "cmm_wc")
    log = logging.getLogger("gwc.test.news")
    # Two listeners beside the lots: one hears the news whole, one about wc1 only (the kernel filters).
    with (
        BlockingBus("obs.whole", cell.cfg.bus, log, interest=NEWS) as whole,
        BlockingBus("obs.wc1", cell.cfg.bus, log, interest=()) as wc1,
    ):
        wc1.set_interest((), subjects=dict.fromkeys(NEWS, ("wc1",)))
        wait_for(lambda: "obs.wc1" in cell.bus.peers(), 10, "the wc1 listener to be known")
        entities = order(cell, "milled_pawn=4")
        import_export_all(cell, entities, timeout=90)
        everything, about_wc1 = heard(whole), heard(wc1)
        read = wc1.bus.stats["msg"]
    assert {"wc1", "wc2", "cmm_wc"} <= set(everything), everything
    assert about_wc1 and about_wc1 == [m for m in everything if m == "wc1"]
    assert read == len(about_wc1) + wc1.bus.stats["duplicates"], (
        "the kernel kept the other machines' news from the wc1 listener"
    )
    for e in entities:
        used = {m for s in steps(cell, e) for m in s["machines"]}
        assert set(account(cell, e)) == used, e  # every machine it used, and none other
        # Nothing missed: no fallback to the tables for a Run_Complete or a status change.
        text = lot_log(cell, e)
        assert "no RUN_COMPL came" not in text and "in MACHINE_STATUS" not in text, text
    for module in ("ms", "wc:wc1", "wc:wc2", "wc:cmm_wc"):  # and every listener acknowledged what it heard
        assert "gave up on" not in cell.log_text(module), module
