"""The console's screens without a cell (a private bus nobody else is on, no database): what asks
for confirmation, and that a cell that is not there is said on screen rather than failing."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from textual.widgets import DataTable

from gwc.config import Config
from gwc.console import views
from gwc.console.app import ConsoleApp
from gwc.console.views import Confirm, LiveTable, MachinesView, fill_table
from gwc.log import open_log
from gwc.soak.private_config import private_bus
from gwc.users import Person, Role
from tests.conftest import make_config
from tests.harness import until


def _app(tmp_path: Path) -> ConsoleApp:
    cfg: Config = make_config(tmp_path, None, bus=private_bus(), machine=[{"id": "wc1", "kind": "dummy"}])
    app = ConsoleApp(cfg, open_log("console", cfg.log_dir, "note"))
    app.link.person = Person("tester", Role.admin, "console", managed=False)  # no database here to identify by
    return app


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


def test_maintenance_done_asks_first_and_goes_to_the_machine_server(tmp_path: Path) -> None:
    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            await pilot.pause()
            _show_machine(app, "Idle")
            app.views()["machines"].focus_main()
            await pilot.press("m")
            await until(pilot.pause, lambda: isinstance(app.screen, Confirm), 5, "the question")
            assert "wc1 was maintained" in app.screen.question  # type: ignore[attr-defined]
            await pilot.press("y")
            await until(pilot.pause, lambda: len(app.answers) >= 2, 10, "the answer")
            assert app.answers[-1].text == "maintenance done on wc1: ms is not on the bus: is the cell running?"
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


def _show(app: ConsoleApp, view_name: str, rows: list[dict[str, object]]) -> None:
    view = app.views()[view_name]
    view.rows = rows
    view.fill(rows)
    view.focus_main()


def test_a_cell_not_running_and_its_database_down_are_said_and_every_action_answers_why_not(tmp_path: Path) -> None:
    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            line = lambda name: str(app._lines[name].render())
            await until(pilot.pause, lambda: "database: unreachable" in line("cellstate"), 10, "the database said down")
            assert "cell DOWN" in line("cellstate")
            await until(pilot.pause, lambda: "not on the bus" in line("statusline"), 10, "the status line's absence")
            await pilot.press("2")
            _show(app, "lots", [{"entity": 4, "lot": 1, "state": "waiting_import"}])
            await pilot.press("i")
            await pilot.press("6")
            _show(app, "alarms", [{"alarm_no": 5, "alarm_id": "HOME_CMM"}])
            await pilot.press("c")
            await pilot.press("5")
            held = {"machine_id": "wc1", "entity_id": 3, "entity_state": "failed"}
            _show(
                app,
                "requests",
                [{"request_key": 17, "entity_id": 4, "op_type": "mill", "machines": "wc1"}, {"reserved": held}],
            )
            await pilot.press("c")
            await until(pilot.pause, lambda: isinstance(app.screen, Confirm), 5, "the question")
            await pilot.press("y")
            await until(pilot.pause, lambda: not isinstance(app.screen, Confirm), 5, "the question answered")
            await pilot.press("u")
            await until(pilot.pause, lambda: isinstance(app.screen, Confirm), 5, "the unreserve question")
            await pilot.press("y")
            said = lambda: [a.text for a in app.answers if a.text != "asking the cell ..."]
            await until(pilot.pause, lambda: len(said()) == 4, 10, "four answers")
            assert sorted(said()) == [
                "cancel request 17: msched is not on the bus: is the cell running?",
                "clear alarm 5: cas is not on the bus: is the cell running?",
                "import entity 4: ls is not on the bus: is the cell running?",
                "unreserve wc1: msched is not on the bus: is the cell running?",
            ]
            assert not any(a.ok for a in app.answers if a.text in said())
            await pilot.press("q")

    asyncio.run(drive())


def test_a_fault_in_the_console_itself_is_said_and_it_goes_on(tmp_path: Path, monkeypatch: Any) -> None:
    def broken(*_: object) -> None:
        raise KeyError("machine_id")

    monkeypatch.setattr(MachinesView, "fetch", broken)

    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            app.act(lambda link: link.act("stop machine wc1", lambda: str(1 / 0)))
            await until(pilot.pause, lambda: any("division" in a.text for a in app.answers), 5, "the fault said")
            await until(pilot.pause, lambda: any("reading machines" in a.text for a in app.answers), 5, "the read")
            texts = [a.text for a in app.answers]
            assert any(
                t.startswith("stop machine wc1: failed, ZeroDivisionError") and "console.log" in t for t in texts
            )
            assert "reading machines failed: 'machine_id'" in texts
            assert app.is_running
            await pilot.press("q")

    asyncio.run(drive())


def test_a_configured_machine_the_database_does_not_know_is_listed_as_unknown(tmp_path: Path, monkeypatch: Any) -> None:
    monkeypatch.setattr(views, "machine_rows", lambda conn, cfg, peers: [])

    async def drive() -> None:
        app = _app(tmp_path)
        monkeypatch.setattr(app.link, "read", lambda fn: fn(None))
        async with app.run_test(size=(140, 40)) as pilot:
            view = app.views()["machines"]
            await until(pilot.pause, lambda: view.rows, 5, "MSTT read")
            assert view.rows == [{"machine_id": "wc1", "kind": "dummy", "status": views.UNKNOWN, "wc": "-"}]
            await pilot.press("q")

    asyncio.run(drive())


def test_new_rows_far_below_the_screen_are_added_as_the_table_scrolls_near_them(tmp_path: Path) -> None:
    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(140, 40)) as pilot:
            await pilot.press("2")
            view = app.views()["lots"]
            table = view.query_one(LiveTable)
            _show(app, "lots", [{"entity": e, "state": "running"} for e in range(1, 501)])
            await pilot.pause()
            assert 40 < table.row_count < 200, table.row_count  # the screen and one more, not all 500
            _show(app, "lots", [{"entity": e, "state": "exported" if e == 5 else "running"} for e in range(1, 501)])
            await pilot.pause()
            assert table.get_row("5")[4].plain == "exported"
            for _ in range(20):  # the operator pages down to the end
                await pilot.press("pagedown")
                await pilot.pause()
            await pilot.press("end")
            await until(pilot.pause, lambda: table.row_count == 500, 10, "every row once scrolled near")
            await until(pilot.pause, lambda: view.selected() == view.rows[-1], 10, "the cursor on the last row")
            await pilot.press("q")

    asyncio.run(drive())


def test_the_spc_screen_lists_the_charts_and_draws_the_highlighted_one(tmp_path: Path) -> None:
    async def drive() -> None:
        app = _app(tmp_path)
        async with app.run_test(size=(160, 50)) as pilot:
            await pilot.pause()
            await pilot.press("minus")  # the SPC screen's key
            await pilot.pause()
            assert app.shown_view() == "spc"
            view = app.views()["spc"]
            view.fill([])
            assert "no measured features" in str(view.query_one("#spc-drawing").render())
            view.rows = [
                {"chart": "mazak mill_pawn DIAMETER", "points": 30, "cpk": "1.90", "rules": "WE2", "drawing": "o o x"},
                {"chart": "mazak mill_pawn HEIGHT", "points": 30, "cpk": "2.10", "rules": "-", "drawing": "o o o"},
            ]
            view.fill(view.rows)
            await pilot.pause()
            assert "mazak mill_pawn DIAMETER\no o x" in str(view.query_one("#spc-drawing").render())
            await pilot.press("q")

    asyncio.run(drive())
