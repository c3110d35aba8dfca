"""The console's Textual application: one tab per screen of the thesis's HI (views.py), the status
line always shown.

Views are read again only when the cell says something that concerns them (link.VIEWS_OF), and only
while shown (a hidden view is read when it is shown again), plus once every SAFETY seconds in case a
change was not heard. Every read and every action runs in a worker thread, so the screen never waits
for the cell; a cell that stops and starts under the console is noticed from the bus's membership
and said on the bottom line.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, ClassVar

from rich.text import Text
from textual import on
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.pilot import Pilot
from textual.widgets import Footer, Header, RichLog, Static, TabbedContent, TabPane

from gwc.config import Config
from gwc.console.link import VIEWS_OF, Answer, CellLink, console_log
from gwc.console.record import RecordView
from gwc.console.views import (
    MONITOR_LINES,
    RELOAD_EVERY,
    AlarmsView,
    Confirm,
    EntryView,
    LotsView,
    MachinesView,
    ModulesView,
    MonitorView,
    OrdersView,
    RequestsView,
    later,
)
from gwc.errors import GwcError
from gwc.retry import Deadline

TICK = 0.1  # how often the console takes what it heard on the bus
PEERS_EVERY = 0.5  # how often the bus's membership is looked at (in memory, no traffic)
STATUS_EVERY = 0.5  # the status line is asked of the Status Line Server at most this often
SAFETY = 5.0  # the shown view is read this often even when nothing concerning it was heard
SCREENSHOT_WAIT = 5.0  # a view's read, at most, before its screenshot is taken anyway


class ConsoleApp(App[None]):
    """`gwc console`: the operator's live screens over one cell."""

    TITLE = "GWC console"
    CSS = """
    #tabs { height: 1fr; }
    .help { color: $text-muted; height: auto; }
    .row { height: auto; }
    #answer { height: 1; background: $boost; }
    #statusline { height: 1; background: $primary-background; }
    #cellstate { height: 1; }
    #confirm { width: 70; height: auto; border: thick $error; background: $surface; padding: 1 2; }
    Confirm { align: center middle; }
    #confirm Horizontal { height: auto; margin-top: 1; }
    #quantity { width: 14; }
    EntryView Select { width: 60; }
    """
    VIEWS: ClassVar[list[tuple[str, str]]] = [
        ("machines", "1 Machines"),
        ("lots", "2 Dispatch"),
        ("entry", "3 New order"),
        ("orders", "4 Orders"),
        ("requests", "5 Requests"),
        ("alarms", "6 Alarms"),
        ("modules", "7 Modules"),
        ("monitor", "8 Monitor"),
        ("record", "0 Record"),
    ]
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("q", "quit", "Quit"),
        Binding("r", "reload", "Refresh"),
        Binding("escape", "focus_view", "Leave field", show=False),
        *(Binding(title.split()[0], f"show('{name}')", title, show=False) for name, title in VIEWS),
    ]

    def __init__(self, cfg: Config, log: logging.Logger, narration: bool = False) -> None:
        super().__init__()
        self.cfg = cfg
        self.log_ = log
        self.link = CellLink(cfg, log)
        self.narration = narration
        self.narrated: collections.deque[str] = collections.deque()  # from another thread, shown by tick()
        self.when_ready: list[Callable[[], None]] = []
        self.cell_up: bool | None = None
        self.cell_since = time.strftime("%H:%M:%S")
        self.modules_seen: set[str] = set()
        self.heard_count = 0
        self._status_busy = False
        self._status_last = 0.0
        self._status_again = False
        self.answers: list[Answer] = []

    # ----------------------------------------------------------------- layout

    def compose(self) -> ComposeResult:
        yield Header(show_clock=True)
        with TabbedContent(id="tabs"):
            views: dict[str, Any] = {
                "machines": MachinesView(),
                "lots": LotsView(),
                "entry": EntryView(),
                "orders": OrdersView(),
                "requests": RequestsView(),
                "alarms": AlarmsView(),
                "modules": ModulesView(),
                "monitor": MonitorView(),
                "record": RecordView(),
            }
            for name, title in self.VIEWS:
                with TabPane(title, id=name):
                    yield views[name]
            if self.narration:
                with TabPane("9 Demo", id="demo"):
                    yield RichLog(id="narration", wrap=True, max_lines=MONITOR_LINES)
        yield Static(Text(""), id="answer")
        yield Static(Text("Status line: (asking the Status Line Server)"), id="statusline")
        yield Static(Text(""), id="cellstate")
        yield Footer()

    def views(self) -> dict[str, Any]:
        return self._views

    def shown_view(self) -> str:
        return self._tabs.active

    def on_mount(self) -> None:
        # Kept, not queried: while a question is asked, queries look at the question's screen.
        self._views: dict[str, Any] = {name: self.query_one(f"#view-{name}") for name, _ in self.VIEWS}
        self._tabs = self.query_one(TabbedContent)
        self._lines = {n: self.query_one(f"#{n}", Static) for n in ("answer", "statusline", "cellstate")}
        self._narration = self.query_one("#narration", RichLog) if self.narration else None
        self.sub_title = f"cell {self.cfg.cell_name}, bus {self.cfg.bus.group}:{self.cfg.bus.port}"
        if self.narration:
            self.bind("9", "show('demo')", show=False)
        try:
            self.link.open()
        except GwcError as e:  # no cell key, a bus that cannot be joined: one line, as every gwc command
            self.exit(return_code=1, message=f"gwc: {e}")
            return
        self._views["monitor"].own_name = self.link.name
        self.show_cell_state()
        self.set_interval(TICK, self.tick)
        self.set_interval(PEERS_EVERY, self.look_at_peers)
        self.set_interval(SAFETY, self.safety)
        self.look_at_peers()
        self.views()["machines"].reload()
        self.reload_status_line()
        self.call_after_refresh(self.action_focus_view)
        for fn in self.when_ready:
            fn()

    def on_unmount(self) -> None:
        self.link.close()

    # ----------------------------------------------------------------- keeping the views live

    def tick(self) -> None:
        while self.narrated and self._narration is not None:
            self._narration.write(Text(self.narrated.popleft()))
        heard = self.link.heard()
        if not heard:
            return
        self.heard_count += len(heard)
        stale: set[str] = set()
        for rec in heard:
            stale.update(VIEWS_OF.get(rec.get("class", ""), ()))
        self._views["monitor"].heard(heard, self.shown_view() == "monitor")
        self.make_stale(stale)

    def make_stale(self, names: set[str]) -> None:
        shown = self.shown_view()
        views = self.views()
        for name in names:
            if name == "status":
                self.reload_status_line()
            elif name in views:
                if name == shown:
                    views[name].reload()
                else:
                    views[name].stale = True

    def look_at_peers(self) -> None:
        names = self.link.modules_up()
        if names != self.modules_seen:
            self.modules_seen = names
            self.make_stale({"machines", "modules"})
        up = bool(names)
        if up != self.cell_up:
            if self.cell_up is not None:
                self.notify(
                    "The cell is back on the bus: every view is read again."
                    if up
                    else "The cell left the bus (stopped or dead). The console waits for it.",
                    severity="information" if up else "warning",
                    markup=False,
                )
            self.cell_up = up
            self.cell_since = time.strftime("%H:%M:%S")
            if up:
                self.make_stale({name for name, _ in self.VIEWS} | {"status"})
        self.show_cell_state()

    def safety(self) -> None:
        self.make_stale({self.shown_view(), "status"})

    def show_cell_state(self) -> None:
        if self.cell_up:
            cell = f"cell UP since {self.cell_since}: {len(self.modules_seen)} modules on the bus"
        else:
            cell = f"cell DOWN since {self.cell_since}: no module on the bus; the console waits for it"
        dbs = f"database: {self.link.db_error}" if self.link.db_error else "database: ok"
        self.set_line(
            "cellstate",
            f"{cell} | {dbs} | heard {self.heard_count} messages, read the database {self.link.reads} times",
            "" if self.cell_up else "bold",
        )

    def set_line(self, name: str, text: str, style: str = "") -> None:
        """Change one of the bottom lines, only if it changed. Without a layout: a line is one row high
        whatever it says, and a layout redraws the whole screen (6 ms of CPU against 0.7 ms, headless)."""
        line = self._lines[name]
        if getattr(line, "_gwc_text", None) != (text, style):
            line._gwc_text = (text, style)  # type: ignore[attr-defined]
            line.update(Text(text, style=style), layout=False)

    def reload_status_line(self) -> None:
        if self._status_busy:
            self._status_again = True
            return
        self._status_busy = True
        later(self, self._status_last + STATUS_EVERY, lambda: self.run_worker(self._status_line, thread=True))

    def _status_line(self) -> None:
        self._status_last = time.monotonic()
        text = self.link.status_line()
        self.call_from_thread(self._show_status_line, text)

    def _show_status_line(self, text: str) -> None:
        self.set_line("statusline", f"Status line: {text}")
        self._status_busy = False
        if self._status_again:
            self._status_again = False
            self.reload_status_line()

    # ----------------------------------------------------------------- actions

    def action_show(self, name: str) -> None:
        self._tabs.active = name

    def action_reload(self) -> None:
        self.make_stale({self.shown_view(), "status"})

    def action_focus_view(self) -> None:
        view = self.views().get(self.shown_view())
        if view is not None:
            view.focus_main()

    @on(TabbedContent.TabActivated)
    def tab_shown(self, event: TabbedContent.TabActivated) -> None:
        view = self.views().get(event.pane.id or "")
        if view is None:
            return
        view.focus_main()
        if view.stale or isinstance(view, MonitorView):
            view.reload()

    def act(self, action: Callable[[CellLink], Answer]) -> None:
        """Run one action in a worker thread; its answer goes to the answer line."""
        self.act_many(lambda link: [action(link)])

    def act_many(self, action: Callable[[CellLink], list[Answer]]) -> None:
        def run() -> None:
            for answer in action(self.link):
                self.call_from_thread(self.say, answer)

        self.say(Answer(True, "asking the cell ..."))
        self.run_worker(run, thread=True)

    def confirm(self, question: str, action: Callable[[CellLink], Answer]) -> None:
        """Ask first (a destructive action); act only on yes."""

        def answered(yes: bool | None) -> None:
            if yes:
                self.act(action)
            else:
                self.say(Answer(True, "not done"))

        self.push_screen(Confirm(question), answered)

    def say(self, answer: Answer) -> None:
        self.answers.append(answer)
        self.set_line("answer", answer.text, "" if answer.ok else "bold red")
        if answer.text != "asking the cell ...":
            self.notify(answer.text, severity="information" if answer.ok else "error", markup=False, timeout=6)


def run_beside(cfg: Config, job: Callable[[Callable[[str], None]], bool], echo: Callable[[str], None]) -> bool:
    """The console in the foreground while job(say) runs in a thread, its narration in the console's
    Demo tab; quitting the console leaves the job running, narrating to `echo`. Returns job's result."""
    app = ConsoleApp(cfg, console_log(cfg), narration=True)
    outcome: dict[str, bool] = {}
    console_open = threading.Event()

    def say(text: str) -> None:
        (app.narrated.append if console_open.is_set() else echo)(text)

    def work() -> None:
        try:
            outcome["ok"] = job(say)
        except GwcError as e:
            say(f"failed: {e}")
        except Exception as e:  # a traceback would tear the console's screen: said and logged instead
            app.log_.exception("console: the job beside it failed")
            say(f"failed: {type(e).__name__}: {e} (the traceback is in {app.link.log_path()})")
        say("finished" + ("" if outcome.get("ok") else " (not every lot did)") + ": q quits the console")

    thread = threading.Thread(target=work, name="console-beside", daemon=True)
    app.when_ready += [console_open.set, thread.start]
    app.run()
    console_open.clear()
    while app.narrated:
        echo(app.narrated.popleft())
    if thread.is_alive():
        echo("console closed; the demonstration goes on here")
        thread.join()
    return outcome.get("ok", False)


def screenshot_every_view(folder: Path) -> Callable[[Pilot[object]], Coroutine[Any, Any, None]]:
    """An auto-pilot that shows each view in turn, once it has been read, and saves it as SVG."""

    async def shoot(pilot: Pilot[object]) -> None:
        app = pilot.app
        assert isinstance(app, ConsoleApp)
        for i, (name, _) in enumerate(app.VIEWS, 1):
            await pilot.press(str(i))
            view = app.views()[name]
            deadline = Deadline(SCREENSHOT_WAIT)
            await pilot.pause(RELOAD_EVERY)
            while getattr(view, "_loading", False) and not deadline.expired:
                await pilot.pause(TICK)
            await pilot.pause(TICK)
            app.save_screenshot(f"console-{name}.svg", path=str(folder))
        app.exit()

    return shoot
