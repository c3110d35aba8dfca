"""The console's screens: one Textual widget per screen of the thesis's HI, and the question asked
before a destructive action.

A View shows rows read from the cell: read again (in a worker thread, one read at a time, at most
every RELOAD_EVERY seconds) when the app marks it stale and it is shown; its table is updated cell by
cell. Actions go through the app (act, confirm), which holds the link to the cell.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from datetime import datetime, timedelta
from typing import TYPE_CHECKING, Any, ClassVar, cast

import psycopg
from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widget import Widget
from textual.widgets import Button, DataTable, Input, Label, RichLog, Select, Static
from textual.widgets.data_table import ColumnKey, RowKey

from gwc.cell import cell_status
from gwc.client.alarms import alarm_rows
from gwc.client.machines import MACHINE_COLUMNS, machine_rows
from gwc.client.orders import list_lots, list_orders, rows_of
from gwc.client.requests import request_tables
from gwc.console.link import WAITING, Answer, CellLink
from gwc.hi.monitor import line_of, matches
from gwc.ipc.codes import MachineStatus
from gwc.ipc.names import Conv
from gwc.module import module_name

if TYPE_CHECKING:
    from gwc.console.app import ConsoleApp

# A view is read at most this often, however busy the bus: a table redrawn costs some 30 ms of CPU
# (Textual renders every visible cell again), and the console shares the machine with the cell.
RELOAD_EVERY = 0.4
MONITOR_LINES = 2000
FULL_EVERY = 60.0  # the dispatch list reads every entity this often; only the changed ones between
CHANGE_MARGIN = timedelta(seconds=5)
UNKNOWN = "unknown to the database (not registered by the Machine Server yet)"
IN_A_RUN = {MachineStatus.SETUP, MachineStatus.RUNNING, MachineStatus.SETUP_SHUT, MachineStatus.RUN_SHUT}


def console_of(widget: Widget) -> ConsoleApp:
    """The console app a view belongs to (views live only in it)."""
    return cast("ConsoleApp", widget.app)


def later(widget: Any, at: float, fn: Callable[[], Any]) -> None:
    """fn at monotonic time `at`: now if that has passed (Textual's timers refuse a zero delay)."""
    wait = at - time.monotonic()
    if wait > 0:
        widget.set_timer(wait, fn)
    else:
        fn()


class Confirm(ModalScreen[bool]):
    """A yes/no question before a destructive action."""

    BINDINGS: ClassVar[list[BindingType]] = [("y", "answer(True)", "Yes"), ("n,escape", "answer(False)", "No")]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        with Vertical(id="confirm"):
            yield Label(Text(self.question))
            with Horizontal():
                yield Button("Yes (y)", id="yes", variant="error")
                yield Button("No (n)", id="no", variant="primary")

    def action_answer(self, yes: bool) -> None:
        self.dismiss(yes)

    @on(Button.Pressed)
    def pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "yes")


class View(Vertical):
    """A pane that shows rows read from the cell, read again when stale and shown."""

    name_: ClassVar[str] = ""
    columns: ClassVar[tuple[str, ...]] = ()
    key: ClassVar[str] = ""
    help: ClassVar[str] = ""

    def __init__(self) -> None:
        super().__init__(id=f"view-{self.name_}")
        self.stale = True
        self._loading = False
        self._again = False
        self._last = 0.0
        self.rows: list[dict[str, Any]] = []

    @property
    def console(self) -> ConsoleApp:
        return console_of(self)

    def compose(self) -> ComposeResult:
        yield Static(Text(self.help), classes="help")
        yield LiveTable(id=f"table-{self.name_}", cursor_type="row", zebra_stripes=True)

    def on_mount(self) -> None:
        table = self.query_one(f"#table-{self.name_}", DataTable)
        add_columns(table, self.columns)
        self.watch(table, "scroll_y", lambda _: self.fill(self.rows), init=False)

    def focus_main(self) -> None:
        self.query_one(DataTable).focus()

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        """The view's rows (in a worker thread); None when the database cannot be reached."""
        raise NotImplementedError

    def reload(self) -> None:
        """Read the rows again (in a worker); one read at a time, at most every RELOAD_EVERY seconds."""
        self.stale = False
        if self._loading:
            self._again = True
            return
        self._loading = True
        later(self, self._last + RELOAD_EVERY, self._start)

    def _start(self) -> None:
        self._last = time.monotonic()
        self.console.run_worker(self._fetch, thread=True)

    def _fetch(self) -> None:
        try:
            rows = self.fetch(self.console.link)
        except Exception as e:  # a bad row must not end the console: shown, logged, read again later
            self.console.log_.exception("console: reading view %s failed", self.name_)
            rows = None
            self.console.call_from_thread(self.console.say, Answer(False, f"reading {self.name_} failed: {e}"))
        self.console.call_from_thread(self._show, rows)

    def _show(self, rows: list[dict[str, Any]] | None) -> None:
        self._loading = False
        if rows is not None:
            self.rows = rows
            self.fill(rows)
        if self._again:
            self._again = False
            self.reload()

    def fill(self, rows: list[dict[str, Any]]) -> None:
        fill_table(self.query_one(DataTable), rows, self.columns, self.key)

    def selected(self) -> dict[str, Any] | None:
        return selected_row(self.query_one(DataTable), self.rows, self.key)


class LiveTable(DataTable[Text]):
    """A DataTable in which a changed cell redraws its own row alone. DataTable.update_cell counts an
    update that every one of its render caches is keyed on, so one changed cell draws every visible
    cell again (28 ms of CPU on a 132x36 screen, headless); here the changed rows' cache entries are
    dropped and their regions alone redrawn. This leans on DataTable's caches (Textual 8), so
    tests/unit/test_console_app.py checks that a changed row shows its new value and the others stay."""

    def set_cells(self, changes: dict[str, dict[str, Text]]) -> None:
        """New values for some cells: {row key: {column key: value}} (rows and columns that exist)."""
        wider = {(k, c): v for k, cells in changes.items() for c, v in cells.items() if self._wider(c, v)}
        for (k, c), value in wider.items():  # its column grows: every row moves, all drawn again (rare)
            self.update_cell(k, c, value, update_width=True)
            del changes[k][c]
        changes = {k: cells for k, cells in changes.items() if cells}
        if not changes:
            return
        rows = {RowKey(k) for k in changes}
        for k, cells in changes.items():
            data = self._data[RowKey(k)]
            for column, value in cells.items():
                data[ColumnKey(column)] = value
        indices = {self.get_row_index(k) for k in changes}
        # (Textual's LRUCache has keys() but no iteration of its own.)
        caches: tuple[Any, ...] = (self._cell_render_cache, self._row_render_cache)  # both keyed by row key first
        for cache in caches:
            for key in [key for key in cache.keys() if key[0] in rows]:  # noqa: SIM118
                cache.discard(key)
        for place in [place for place in self._row_renderable_cache.keys() if place[1] in indices]:  # noqa: SIM118
            self._row_renderable_cache.discard(place)
        self._line_cache.clear()  # lines are keyed by their place: those of other rows are made again from their rows
        for index in indices:
            self.refresh_row(index)

    def _wider(self, column: str, value: Text) -> bool:
        return value.cell_len > self.columns[ColumnKey(column)].content_width


def fill_table(table: DataTable[Any], rows: list[dict[str, Any]], columns: tuple[str, ...], key: str) -> None:
    """Show `rows`, touching only what changed and can be seen: a changed row is redrawn (a LiveTable
    redraws it alone; a DataTable every visible cell, some 30 ms of CPU), which a busy cell's machine
    should not pay for rows nobody sees (a row off screen is brought up to date when it scrolls into
    view: fill again then). New rows are added only down to a screen below the one shown (an added row
    draws every visible cell again, DataTable's caches being keyed on its row count too); the others
    come as the table scrolls near them. A table whose rows were removed or reordered is filled again, keeping the
    cursor on the same row (by key)."""
    shown: dict[str, tuple[str, ...]] = table.__dict__.setdefault("_gwc_shown", {})
    new = {str(r[key]): tuple("" if r.get(c) is None else str(r.get(c)) for c in columns) for r in rows}
    if list(new)[: len(shown)] != list(shown):
        current = selected_key(table)
        table.clear()
        shown.clear()
        for k, cells in new.items():
            table.add_row(*map(Text, cells), key=k)
            shown[k] = cells
        if current in shown:
            table.move_cursor(row=table.get_row_index(current))
        return
    # The screen's height bounds what can be seen of the table (its own grows with its rows, up to its pane).
    top, height = int(table.scroll_y), table.app.size.height
    changes: dict[str, dict[str, Text]] = {}
    for index, (k, cells) in enumerate(new.items()):
        before = shown.get(k)
        if before is None:
            if height and index > top + 2 * height:
                break  # a screen below the last one seen: added as they scroll near (and all after it: new too)
            table.add_row(*map(Text, cells), key=k)
        elif cells != before:
            if height and not top - 1 <= index <= top + height:
                continue  # off screen: left as it was (and as `shown` says it is) until it is seen
            changes[k] = {c: Text(v) for c, old_value, v in zip(columns, before, cells) if v != old_value}
        shown[k] = cells
    if isinstance(table, LiveTable):
        table.set_cells(changes)
    else:
        for k, changed in changes.items():
            for column, value in changed.items():
                table.update_cell(k, column, value)


def add_columns(table: DataTable[Any], columns: tuple[str, ...]) -> None:
    for c in columns:
        table.add_column(c, key=c)  # keyed by name, for update_cell


def selected_key(table: DataTable[Any]) -> str | None:
    if not table.row_count:
        return None
    return table.coordinate_to_cell_key(table.cursor_coordinate).row_key.value


def selected_row(table: DataTable[Any], rows: list[dict[str, Any]], key: str) -> dict[str, Any] | None:
    k = selected_key(table)
    return next((r for r in rows if str(r[key]) == k), None)


class MachinesView(View):
    name_ = "machines"
    columns = MACHINE_COLUMNS
    key = "machine_id"
    help = (
        "MSTT: each machine's status, its current run, what it accepts and its books.  s start  x stop  "
        "m maintenance done"
    )
    BINDINGS: ClassVar[list[BindingType]] = [
        ("s", "start", "Start machine"),
        ("x", "stop", "Stop machine"),
        ("m", "maintained", "Maintenance done"),
    ]

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        peers = set(link.peers())
        rows = link.read(lambda conn: machine_rows(conn, link.cfg, peers))
        if rows is None:
            return None
        # A machine of cell.toml that MACHINE_STATUS does not hold yet (the Machine Server registers it
        # at its start): listed as such rather than left out.
        known = {r["machine_id"] for r in rows}
        unknown = [
            {
                "machine_id": m.id,
                "kind": m.kind,
                "status": UNKNOWN,
                "wc": "on bus" if module_name("wc", m.id) in peers else "-",
            }
            for m in link.cfg.machines
            if m.id not in known
        ]
        return sorted(rows + unknown, key=lambda r: str(r["machine_id"]))

    def action_start(self) -> None:
        row = self.selected()
        if row:
            self.console.act(lambda link: link.start_machine(row["machine_id"]))

    def action_maintained(self) -> None:
        row = self.selected()
        if row:
            mid = row["machine_id"]
            self.console.confirm(
                f"Machine {mid} was maintained? Its count of runs since maintenance ({row.get('runs', '?')}) "
                "starts again.",
                lambda link: link.maintenance_done(mid),
            )

    def action_stop(self) -> None:
        row = self.selected()
        if not row:
            return
        mid = row["machine_id"]
        if row["status"] in IN_A_RUN:
            self.console.confirm(
                f"Machine {mid} is {row['status']} (run {row['machine_run_id']}). Stop it? "
                "It shuts down when the run is over.",
                lambda link: link.stop_machine(mid),
            )
        else:
            self.console.act(lambda link: link.stop_machine(mid))


class LotsView(View):
    name_ = "lots"
    columns = ("entity", "lot", "work_order", "product", "state", "since", "script", "result")
    key = "entity"
    help = "DISP: every lot entity.  i import  e export (the selected entity)  I import all waiting  E export all"
    BINDINGS: ClassVar[list[BindingType]] = [
        ("i", "decide('import')", "Import"),
        ("e", "decide('export')", "Export"),
        ("I", "decide_all('import')", "Import all"),
        ("E", "decide_all('export')", "Export all"),
    ]

    def __init__(self) -> None:
        super().__init__()
        self._known: dict[int, dict[str, Any]] = {}
        self._since: datetime | None = None  # the database's clock at the last read
        self._full_at = 0.0

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        """Only the entities changed since the last read (LOT_STATUS.updated_at, less a margin for a
        transaction that began before it and committed after), all of them every FULL_EVERY seconds:
        a cell that ran for months has many lots, and the console reads often."""
        full = self._since is None or time.monotonic() > self._full_at + FULL_EVERY
        since = None if full or self._since is None else self._since - CHANGE_MARGIN

        def read(conn: psycopg.Connection[Any]) -> tuple[datetime, list[dict[str, Any]]]:
            row = conn.execute("SELECT now()").fetchone()  # the read's transaction's start (CellLink.read)
            assert row is not None  # SELECT now() always has its row
            now: datetime = row[0]
            return now, list_lots(link.cfg, link.log, conn=conn, changed_since=since)

        got = link.read(read)
        if got is None:
            self._since = None  # the next read after an outage is a full one
            return None
        self._since, rows = got
        if full:
            self._known = {}
            self._full_at = time.monotonic()
        self._known.update((r["entity"], r) for r in rows)
        return [self._known[e] for e in sorted(self._known)]

    def action_decide(self, action: str) -> None:
        row = self.selected()
        if row:
            self.console.act(lambda link: link.decide(row["entity"], action))

    def action_decide_all(self, action: str) -> None:
        entities = [r["entity"] for r in self.rows if r["state"] == WAITING[action]]
        if not entities:
            self.console.say(Answer(False, f"no entity waits to be {action}ed"))
            return
        self.console.act_many(lambda link: link.decide_all(action, entities))


class OrdersView(View):
    name_ = "orders"
    columns = ("work_order", "customer", "customer_name", "due", "items", "status", "lots")
    key = "work_order"
    help = "WOSU: every work order, its items and where its lots are."

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        return link.read(lambda conn: list_orders(link.cfg, link.log, conn=conn))


class RequestsView(View):
    name_ = "requests"
    columns = ("request_key", "lot_id", "entity_id", "op_type", "machines", "priority", "since")
    reserved_columns = ("machine_id", "lot_id", "entity_id", "entity_state", "machine_run_id", "request_key", "since")
    key = "request_key"
    help = (
        "MREQ: machine requests waiting (oldest first), then the reserved machines.  c cancel the request  "
        "u unreserve the reserved machine (its lot script dead)"
    )
    BINDINGS: ClassVar[list[BindingType]] = [("c", "cancel", "Cancel request"), ("u", "unreserve", "Unreserve")]

    def compose(self) -> ComposeResult:
        yield from super().compose()
        yield Static(Text("Reserved machines"), classes="help")
        yield LiveTable(id="table-reserved", cursor_type="row", zebra_stripes=True)

    def on_mount(self) -> None:  # View's on_mount has run too (Textual calls each class's handler)
        add_columns(self.query_one("#table-reserved", DataTable), self.reserved_columns)

    def focus_main(self) -> None:
        self.query_one(f"#table-{self.name_}", DataTable).focus()

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        tables = link.read(request_tables)
        if tables is None:
            return None
        queue, reserved, _ = tables
        return [*queue, *({"reserved": r} for r in reserved)]

    def fill(self, rows: list[dict[str, Any]]) -> None:
        queue = [r for r in rows if "reserved" not in r]
        reserved = [r["reserved"] for r in rows if "reserved" in r]
        fill_table(self.query_one(f"#table-{self.name_}", DataTable), queue, self.columns, self.key)
        fill_table(self.query_one("#table-reserved", DataTable), reserved, self.reserved_columns, "machine_id")

    def selected(self) -> dict[str, Any] | None:
        queue = [r for r in self.rows if "reserved" not in r]
        return selected_row(self.query_one(f"#table-{self.name_}", DataTable), queue, self.key)

    def action_unreserve(self) -> None:
        reserved = [r["reserved"] for r in self.rows if "reserved" in r]
        row = selected_row(self.query_one("#table-reserved", DataTable), reserved, "machine_id")
        if row:
            machine = row["machine_id"]
            self.console.confirm(
                f"Unreserve {machine}, held by entity {row['entity_id']} ({row['entity_state']})? Only for an "
                "entity whose lot script died: MSCHED may give the machine to the next request.",
                lambda link: link.unreserve_machine(machine),
            )

    def action_cancel(self) -> None:
        row = self.selected()
        if row:
            key = row["request_key"]
            self.console.confirm(
                f"Cancel request {key} of entity {row['entity_id']} ({row['op_type']} on {row['machines']})? "
                "The entity is told REQ_CANCEL.",
                lambda link: link.cancel_request(key),
            )


class AlarmsView(View):
    name_ = "alarms"
    columns = ("alarm_no", "alarm_id", "machine_id", "alarm_text", "raised_by", "raised_at")
    key = "alarm_no"
    help = "Pending alarms, oldest first (a machine may wait on one).  c clear the alarm"
    BINDINGS: ClassVar[list[BindingType]] = [("c", "clear", "Clear alarm")]

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        return link.read(alarm_rows)

    def action_clear(self) -> None:
        row = self.selected()
        if row:
            self.console.act(lambda link: link.clear_alarm(row["alarm_no"]))


class ModulesView(View):
    name_ = "modules"
    columns = ("module", "state", "pid", "uptime", "restarts", "last_exit", "bus")
    key = "module"
    help = (
        "STRT: the cell's modules (under this host's agent where one runs).  s start  x stop  R restart  "
        "S start the cell"
    )
    BINDINGS: ClassVar[list[BindingType]] = [
        ("s", "start", "Start"),
        ("x", "stop", "Stop"),
        ("R", "restart", "Restart"),
        ("S", "start_cell", "Start cell"),
    ]

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        peers = link.peers()
        agent, rows = cell_status(link.cfg)
        for r in rows:
            peer = peers.get(r["module"])
            if peer is None:
                r["bus"] = "-"
            elif r["module"].startswith("wc:"):
                r["bus"] = "on bus"
            else:
                r["bus"] = "started" if Conv.SHUTDOWN in peer.interest else "on bus, not started"
        agent_row = {"module": "agent", "state": "RUNNING" if agent else "not running (unsupervised)"}
        return [{**agent_row, **(agent or {}), "module": "agent"}, *rows]

    def action_start(self) -> None:
        row = self.selected()
        if row and row["module"] != "agent":
            self.console.act(lambda link: link.start_module(row["module"]))

    def action_stop(self) -> None:
        row = self.selected()
        if row and row["module"] != "agent":
            name = row["module"]
            self.console.confirm(f"Stop {name}?", lambda link: link.stop_module(name))

    def action_restart(self) -> None:
        row = self.selected()
        if row and row["module"] != "agent":
            name = row["module"]
            self.console.confirm(
                f"Restart {name} (stop its process, start it again)?", lambda link: link.restart_module(name)
            )

    def action_start_cell(self) -> None:
        self.console.act(lambda link: link.start_cell())


class EntryView(Vertical):
    """WOEN: a work order from a customer and product pickers; each item adds a lot."""

    BINDINGS: ClassVar[list[BindingType]] = [Binding("ctrl+s", "enter_order", "Enter order", priority=True)]

    def __init__(self) -> None:
        super().__init__(id="view-entry")
        self.items: list[tuple[str, int]] = []
        self.stale = True

    def compose(self) -> ComposeResult:
        yield Static(Text("WOEN: pick a customer and products, then Enter order (ctrl+s)."), classes="help")
        yield Select([], prompt="Customer", id="customer")
        with Horizontal(classes="row"):
            yield Select([], prompt="Product", id="product")
            yield Input("1", placeholder="quantity", type="integer", id="quantity")
            yield Button("Add item", id="add")
        yield Static(Text("items: (none yet: the product above is ordered)"), id="items")
        yield Button("Enter order", id="enter", variant="success")

    def focus_main(self) -> None:
        self.query_one("#customer", Select).focus()

    def reload(self) -> None:
        """The pickers' choices, from CUSTOMERS and PRODUCTS (read when the form is shown)."""
        self.stale = False
        app = console_of(self)
        app.run_worker(self._fetch, thread=True)

    def _fetch(self) -> None:
        app = console_of(self)

        def read(conn: psycopg.Connection[Any]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
            return (
                rows_of(conn, "SELECT customer_id, name FROM customers ORDER BY 1"),
                rows_of(conn, "SELECT product_id, description FROM products WHERE script_id IS NOT NULL ORDER BY 1"),
            )

        try:
            got = app.link.read(read)
        except Exception as e:  # a bad row must not end the console: shown, logged, read again when shown
            app.log_.exception("console: reading the order form's choices failed")
            self.stale = True
            app.call_from_thread(app.say, Answer(False, f"reading the customers and products failed: {e}"))
            return
        if got is not None:
            app.call_from_thread(self._options, *got)

    def _options(self, customers: list[dict[str, Any]], products: list[dict[str, Any]]) -> None:
        for widget, rows, key, label in (
            (self.query_one("#customer", Select), customers, "customer_id", "name"),
            (self.query_one("#product", Select), products, "product_id", "description"),
        ):
            value = widget.value
            widget.set_options([(f"{r[key]}  {r[label] or ''}".rstrip(), r[key]) for r in rows])
            if any(r[key] == value for r in rows):
                widget.value = value

    def _current(self) -> tuple[str, int] | None:
        product = self.query_one("#product", Select).value
        try:
            qty = int(self.query_one("#quantity", Input).value)
        except ValueError:
            qty = 0
        if product is Select.NULL or qty < 1:
            return None
        return str(product), qty

    def _show_items(self) -> None:
        text = ", ".join(f"{q} x {p}" for p, q in self.items) or "(none yet: the product above is ordered)"
        self.query_one("#items", Static).update(Text(f"items: {text}"))

    @on(Button.Pressed, "#add")
    def add(self) -> None:
        item = self._current()
        app = console_of(self)
        if item is None:
            app.say(Answer(False, "pick a product and a quantity of 1 or more"))
            return
        self.items.append(item)
        self._show_items()

    @on(Button.Pressed, "#enter")
    def action_enter_order(self) -> None:
        app = console_of(self)
        customer = self.query_one("#customer", Select).value
        items = self.items or ([c] if (c := self._current()) else [])
        if customer is Select.NULL or not items:
            app.say(Answer(False, "a work order needs a customer and at least one product"))
            return
        self.items = []
        self._show_items()
        app.act(lambda link: link.enter_order(str(customer), items))


class MonitorView(Vertical):
    """The Conversation Monitor inside the console, with its filters (class, module, machine)."""

    def __init__(self) -> None:
        super().__init__(id="view-monitor")
        self.records: collections.deque[dict[str, Any]] = collections.deque(maxlen=MONITOR_LINES)
        self.filters: tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]] = ((), (), ())
        self.machine_convs: set[str] = set()
        self.stale = False
        self.own_name = ""

    def compose(self) -> ComposeResult:
        yield Static(Text("Every conversation on the bus. Filters (comma-separated, empty: all):"), classes="help")
        with Horizontal(classes="row"):
            yield Input(placeholder="class, e.g. MACH_REQ", id="f-class")
            yield Input(placeholder="module, e.g. msched", id="f-module")
            yield Input(placeholder="machine, e.g. wc1", id="f-machine")
        yield RichLog(id="monitor-log", max_lines=MONITOR_LINES, wrap=False)

    def focus_main(self) -> None:
        self.query_one("#f-class", Input).focus()

    def reload(self) -> None:
        self._redraw()

    def _match(self, rec: dict[str, Any]) -> bool:
        # The console's own status-line asks are left out: they would drown a quiet cell's conversations.
        own = rec.get("initiator") == self.own_name and rec.get("class") == Conv.STATUS_LN
        return "message" in rec and not own and matches(rec, *self.filters, self.machine_convs)

    def heard(self, records: list[dict[str, Any]], shown: bool) -> None:
        self.records.extend(records)
        if shown:
            log = self.query_one(RichLog)
            for rec in records[-MONITOR_LINES:]:
                if self._match(rec):
                    log.write(Text(line_of(rec)))

    def _redraw(self) -> None:
        log = self.query_one(RichLog)
        log.clear()
        self.machine_convs = set()
        for rec in self.records:
            if self._match(rec):
                log.write(Text(line_of(rec)))

    @on(Input.Changed)
    def filter_changed(self) -> None:
        def split(widget_id: str) -> tuple[str, ...]:
            return tuple(x.strip() for x in self.query_one(widget_id, Input).value.split(",") if x.strip())

        self.filters = (split("#f-class"), split("#f-module"), split("#f-machine"))
        self._redraw()
