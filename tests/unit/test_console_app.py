"""The console's screens without a cell (a private bus nobody else is on, no database): what asks
for confirmation, and that a cell that is not there is said on screen rather than failing."""

from __future__ import annotations

import asyncio
from pathlib import Path

from textual.widgets import DataTable

from gwc.config import Config, private_bus
from gwc.console.app import ConsoleApp
from gwc.console.views import Confirm, LiveTable, fill_table
from gwc.log import open_log
from tests.conftest import make_config
from tests.harness import until


def _app(tmp_path: Path) -> ConsoleApp:
    cfg: Config = make_config(tmp_path, None, bus=private_bus(), machine=[{"id": "wc1", "kind": "dummy"}])
    return ConsoleApp(cfg, open_log("console", cfg.log_dir, "note"))


def _show_machine(app: ConsoleApp, status: str) -> None:
    view = app.views()["machines"]
    view.rows = [{"machine_id": "wc1", "kind": "dummy", "status": status, "machine_run_id": 7}]
    fill_table(view.query_one(DataTable), view.rows, view.columns, view.key)


def test_stopping_a_machine_in_a_run_asks_first_and_no_does_nothing(tmp_path: Path) -> None:
    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            await pilot.pause()
            assert "cell DOWN" in str(app._lines["cellstate"].render())
            _show_machine(app, "Running")
            app.views()["machines"].focus_main()
            await pilot.press("x")
            await pilot.pause()
            assert isinstance(app.screen, Confirm) and "Running (run 7)" in app.screen.question
            await pilot.press("n")
            await pilot.pause()
            assert not isinstance(app.screen, Confirm)
            assert [a.text for a in app.answers] == ["not done"]
            await pilot.press("q")

    asyncio.run(drive())


def test_stopping_an_idle_machine_asks_nothing_and_says_why_it_cannot(tmp_path: Path) -> None:
    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            await pilot.pause()
            _show_machine(app, "Idle")
            app.views()["machines"].focus_main()
            await pilot.press("x")
            await pilot.pause()
            assert not isinstance(app.screen, Confirm)
            # "asking the cell ...", then the answer (the WC is looked for on the bus for 2 s)
            await until(pilot.pause, lambda: len(app.answers) >= 2, 10, "the answer")
            said = app.answers[-1].text
            assert said == "stop machine wc1 (ME_SHUT): wc:wc1 is not on the bus: the machine is not running"
            assert not app.answers[-1].ok
            await pilot.press("q")

    asyncio.run(drive())


def test_a_changed_row_is_drawn_with_its_new_value_and_the_others_as_they_were(tmp_path: Path) -> None:
    """LiveTable redraws a changed row alone by dropping its entries from DataTable's caches: a Textual
    whose caches changed would show stale rows, which this catches. A value wider than its column
    widens it."""

    def lots(states: dict[int, str]) -> list[dict[str, object]]:
        return [{"entity": e, "lot": 1, "product": "pawn", "state": s} for e, s in states.items()]

    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            await pilot.press("2")
            view = app.views()["lots"]
            table = view.query_one(LiveTable)
            states = {e: "waiting_import" if e == 1 else "running" for e in range(1, 30)}
            view.rows = lots(states)
            view.fill(view.rows)
            await pilot.pause()
            before = [table.render_line(y).text for y in range(1, 30)]  # line 0 is the header
            states[3], states[7] = "waiting_export", "exported"
            view.rows = lots(states)
            view.fill(view.rows)
            await pilot.pause()
            after = [table.render_line(y).text for y in range(1, 30)]
            assert "waiting_export" in after[2] and "exported" in after[6], after[:8]
            assert [a for i, a in enumerate(after) if i not in (2, 6)] == [
                b for i, b in enumerate(before) if i not in (2, 6)
            ]
            assert table.get_row("3")[4].plain == "waiting_export"
            states[9] = "a state wider than any before"  # its column grows: drawn whole
            view.rows = lots(states)
            view.fill(view.rows)
            await pilot.pause()
            assert "a state wider than any before" in table.render_line(9).text
            await pilot.press("q")

    asyncio.run(drive())
