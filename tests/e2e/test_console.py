"""`gwc console` against a real running cell: Textual's pilot drives the app in this process, the
cell's modules are real processes; the checks look at the cell (its tables, `gwc` commands), not at
the console's own idea of it. One run in a real terminal (tmux) proves `gwc console` as typed."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from textual.widgets import DataTable, Input, Select

from gwc.console.app import ConsoleApp
from gwc.console.terminal import Terminal, have_tmux
from gwc.ipc.catalogue import message
from gwc.log import open_log
from tests.e2e.lotkit import gwc, ok
from tests.e2e.test_demo import demo_env  # noqa: F401 (the fixture)
from tests.harness import SERVERS, CellHarness, until, wait_for

pytestmark = pytest.mark.e2e

MACHINES = [{"id": "wc1", "kind": "dummy", "run_time": 0.2}, {"id": "wc2", "kind": "dummy", "run_time": 0.2}]


def table_keys(app: ConsoleApp, table_id: str) -> list[str]:
    table = app._views[table_id].query_one(f"#table-{table_id}", DataTable)
    return [str(k.value) for k in table.rows]


def select_row(app: ConsoleApp, view: str, key: str) -> None:
    table = app._views[view].query_one(f"#table-{view}", DataTable)
    table.move_cursor(row=table.get_row_index(key))


def console(cell: CellHarness) -> ConsoleApp:
    return ConsoleApp(cell.cfg, open_log("console", cell.cfg.log_dir, "note"))


def lot_states(cell: CellHarness) -> dict[int, str]:
    return {e: s for e, s in cell.query("SELECT entity_id, state FROM lot_status")}


def test_order_entered_in_the_form_makes_its_lots_and_a_waiting_lot_is_imported_with_one_key(lot_cell: Any) -> None:
    cell = lot_cell(machines=MACHINES)
    cell.start_servers()

    async def drive() -> None:
        app = console(cell)
        async with app.run_test(size=(160, 45)) as pilot:
            await pilot.press("3")  # WOEN
            customer, product = app.query_one("#customer", Select), app.query_one("#product", Select)
            await until(pilot.pause, lambda: len(product._options) > 1, 10, "the product picker to be filled")
            customer.value = "NJIT"
            product.value = "milled_pawn"
            app.query_one("#quantity", Input).value = "2"
            await pilot.press("ctrl+s")
            answer = await until(pilot.pause, lambda: [a for a in app.answers if "work order" in a.text], 30, "answer")
            assert answer[0].ok, answer[0].text
            entities = sorted(lot_states(cell))
            assert len(entities) == 2, answer[0].text

            await pilot.press("2")  # DISP: the lots appear as they ask to be imported
            await until(
                pilot.pause,
                lambda: (
                    all(lot_states(cell).get(e) == "waiting_import" for e in entities)
                    and {str(e) for e in entities} <= set(table_keys(app, "lots"))
                ),
                20,
                "both lots listed, waiting for import",
            )
            await until(
                pilot.pause,
                lambda: [r for r in app._views["lots"].rows if r["state"] == "waiting_import"],
                2,
                "the dispatch list to show them waiting",
            )
            select_row(app, "lots", str(entities[0]))
            await pilot.press("i")  # one key
            await until(pilot.pause, lambda: lot_states(cell)[entities[0]] != "waiting_import", 15, "the import")
            assert lot_states(cell)[entities[1]] == "waiting_import"
            assert any(a.ok and f"import entity {entities[0]}: ACK_OK (done)" in a.text for a in app.answers)
            # The view follows the cell by itself (the bus said so), within half a second.
            imported = time.monotonic()
            await until(
                pilot.pause,
                lambda: (
                    next(r for r in app._views["lots"].rows if r["entity"] == entities[0])["state"] != "waiting_import"
                ),
                5,
                "the dispatch list to show the import",
            )
            assert time.monotonic() - imported < 1.0
            await pilot.press("q")

    asyncio.run(drive())


def test_machine_stopped_and_alarm_cleared_from_the_console_change_the_cell(cell: CellHarness) -> None:
    cell.start_servers()
    cell.start_machine_processes("wc1")
    conv, batch = cell.bus.request("ME_START", message("Startup_Request", module="wc:wc1"), to="wc:wc1")
    conv.end()
    wait_for(lambda: cell.query("SELECT status FROM machine_status WHERE machine_id='wc1'") == [("Idle",)], 20, "Idle")
    conv, batch = cell.bus.request(
        "ALARM_SEND", message("Alarm_Send", alarm_id="HOME_CMM", machine_id="wc1", raised_by="test"), to="cas"
    )
    conv.end()
    alarm_no = batch.first.alarm_no

    async def drive() -> None:
        app = console(cell)
        async with app.run_test(size=(160, 45)) as pilot:
            await until(pilot.pause, lambda: "Idle" in str(app._views["machines"].rows), 10, "wc1 Idle in MSTT")
            select_row(app, "machines", "wc1")
            await pilot.press("x")  # Idle: no run to lose, no question
            await until(pilot.pause, lambda: any("stop machine wc1" in a.text for a in app.answers), 30, "the answer")
            assert [a.text for a in app.answers if "stop machine wc1" in a.text] == [
                "stop machine wc1 (ME_SHUT): shut down"
            ]
            await until(
                pilot, lambda: "Shutdown" in str(app._views["machines"].rows), 2, "MSTT to show Shutdown by itself"
            )

            await pilot.press("6")
            await until(pilot.pause, lambda: str(alarm_no) in table_keys(app, "alarms"), 10, "the alarm listed")
            select_row(app, "alarms", str(alarm_no))
            await pilot.press("c")
            await until(pilot.pause, lambda: any("clear alarm" in a.text for a in app.answers), 15, "the answer")
            assert any(a.text == f"clear alarm {alarm_no}: ACK_OK (done)" for a in app.answers), app.answers
            await until(pilot.pause, lambda: str(alarm_no) not in table_keys(app, "alarms"), 2, "the alarm to go")

            # A bus peer dies (kill -9: no bye): the console says so, and an action that needs it answers why not.
            await asyncio.to_thread(cell.kill, "cas")
            await until(pilot.pause, lambda: "cas" not in app.modules_seen, 10, "the console to see cas gone")
            app.act(lambda link: link.clear_alarm(alarm_no + 1))
            asked = f"clear alarm {alarm_no + 1}: "
            answer = await until(pilot.pause, lambda: [a for a in app.answers if a.text.startswith(asked)], 10, "it")
            assert answer[0].text == f"{asked}cas is not on the bus: is the cell running?", answer[0].text
            await pilot.press("7")
            await until(
                pilot.pause,
                lambda: [r for r in app._views["modules"].rows if r["module"] == "cas" and r["bus"] == "-"],
                10,
                "STRT to show cas off the bus",
            )
            await pilot.press("q")

    asyncio.run(drive())
    status = {r["machine_id"]: r["status"] for r in json.loads(ok(gwc(cell, "machine", "status", "--json")))}
    assert status["wc1"] == "Shutdown"
    assert json.loads(ok(gwc(cell, "alarm", "list", "--json"))) == []
    assert cell.query("SELECT cleared_by FROM alarms WHERE alarm_no = %s", alarm_no)[0][0].startswith("console:")


needs_tmux = pytest.mark.skipif(not have_tmux(), reason="no tmux (bin/setup installs it when run as root)")


@needs_tmux
def test_gwc_console_in_a_terminal_shows_every_machine_survives_the_cell_stopping_and_quits_on_q(
    make_cell: Any,
) -> None:
    cell = make_cell(machines=MACHINES)
    cell.start_servers()
    for m in MACHINES:
        cell.start_machine_processes(m["id"])
    term = Terminal(f"gwc-console-{cell.tag}", cell.env(), "console")
    try:
        term.wait("every machine in MSTT", "wc1", "wc2", "Shutdown", "cell UP")
        # The cell stops under the console (every module on the bus goes), then starts again.
        bus_modules = [*((s, None) for s in SERVERS), *(("wc", m["id"]) for m in MACHINES)]
        for kind, machine in reversed(bus_modules):
            cell.kill(kind, machine, sig=signal.SIGTERM)
        term.wait("the console to say the cell is down", "cell DOWN")
        cell.start_servers()
        for m in MACHINES:
            cell.start("wc", m["id"], start=False)
        term.wait("the console to say the cell is back", "cell UP", "wc1", "wc2")
        term.keys("q")
        assert term.exit_code() == 0
    finally:
        term.close()


def demo_in_console(demo_env: tuple[Path, dict[str, str]], *order: str, timeout: float) -> None:
    """`gwc demo --console` in a real terminal: the console shows the demonstration's machines, its
    narration (tab 9) runs to a successful end, the console sees the cell stopped, q quits, exit 0."""
    config, env = demo_env
    term = Terminal(f"gwc-demo-console-{os.getpid()}", env, "demo", "--config", str(config), "--console", *order)
    try:
        term.wait("the demonstration's machines in MSTT", "cell UP", "cmm_wc", "mazak", "wc2", timeout=90)
        term.keys("9")
        # The cell's start comes first (12 s quiet, over 30 s seen at load 15), then the operator's part.
        term.wait("the narration in the Demo tab", "operator: start machine", timeout=timeout)
        term.wait("the demonstration to finish", "finished: q quits the console", timeout=timeout)
        screen = term.screen()
        assert "demonstration succeeded" in screen and "not every lot did" not in screen, screen
        term.wait("the console to see the cell stopped", "cell DOWN")
        term.keys("q")
        assert term.exit_code() == 0  # the demonstration's own verdict: every lot exported, every invariant kept
    finally:
        term.close()


@needs_tmux
def test_gwc_demo_console_shows_a_one_pawn_demonstration_live_and_it_succeeds(
    demo_env: tuple[Path, dict[str, str]],
) -> None:
    # One pawn (milled, measured) and the mills swapped while it runs: about 15 s, most of it the cell starting.
    demo_in_console(demo_env, "--chess", "0", "--pawns", "1", timeout=200)


@pytest.mark.soak  # the whole demonstration a newcomer runs (5 lots, about 30 s): more than the suite can spare
@pytest.mark.timeout(600)
@needs_tmux
def test_gwc_demo_console_shows_the_whole_demonstration_live_and_it_succeeds(
    demo_env: tuple[Path, dict[str, str]],
) -> None:
    # A demonstration takes 30 s on a quiet machine, and was seen to take 214 s on a loaded one.
    demo_in_console(demo_env, timeout=400)
