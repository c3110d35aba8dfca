"""The console's Record screen (docs/record.md): downtime events, newest first, with the reason the
operator gives them from the reason tree; under them OEE per machine and for the cell since midnight.

`r` asks for the selected event's reason (a list of the tree's reasons) and sends it to the Machine
Server (DOWNTIME_RSN), as `gwc downtime reason` does.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

import psycopg
from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import BindingType
from textual.containers import Vertical
from textual.screen import ModalScreen
from textual.widgets import DataTable, Label, OptionList, Static

from gwc.client.record import parse_when, set_downtime_reason
from gwc.console.link import Answer, CellLink, operator
from gwc.console.views import LiveTable, View, add_columns, fill_table, selected_row
from gwc.record import store

OEE_COLUMNS = ("machine_id", "availability", "performance", "quality", "oee", "run_s", "down_s", "parts", "good_parts")


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


class ReasonPicker(ModalScreen[str | None]):
    """The reason tree as one list: category, then its reasons; Enter picks, Escape leaves it."""

    BINDINGS: ClassVar[list[BindingType]] = [("escape", "dismiss_none", "Leave")]

    def __init__(self, event_id: int, tree: dict[str, list[str]]) -> None:
        super().__init__()
        self.event_id = event_id
        self.reasons = [r for rs in tree.values() for r in rs]
        self.labels = [f"{c}: {r}" for c, rs in tree.items() for r in rs]

    def compose(self) -> ComposeResult:
        with Vertical(id="confirm"):
            yield Label(Text(f"Reason of downtime {self.event_id} (Enter picks, Escape leaves):"))
            yield OptionList(*self.labels, id="reasons")

    def action_dismiss_none(self) -> None:
        self.dismiss(None)

    @on(OptionList.OptionSelected)
    def picked(self, event: OptionList.OptionSelected) -> None:
        self.dismiss(self.reasons[event.option_index])


class RecordView(View):
    name_ = "record"
    columns = ("event_id", "machine_id", "started_at", "ended_at", "cause", "reason", "e10_state")
    key = "event_id"
    help = "Downtime events (open ones first), then OEE since midnight.  r give the selected stop its reason"
    BINDINGS: ClassVar[list[BindingType]] = [("r", "reason", "Downtime reason")]

    def compose(self) -> ComposeResult:
        yield from super().compose()
        yield Static(Text("OEE since midnight (availability x performance x quality)"), classes="help")
        yield LiveTable(id="table-oee", cursor_type="row", zebra_stripes=True)

    def on_mount(self) -> None:  # View's on_mount has run too
        add_columns(self.query_one("#table-oee", DataTable), OEE_COLUMNS)

    def focus_main(self) -> None:
        self.query_one(f"#table-{self.name_}", DataTable).focus()

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        rec = link.cfg.record
        until = datetime.now(UTC)
        since = parse_when("today", rec.timezone, until)

        def read(conn: psycopg.Connection[Any]) -> list[dict[str, Any]]:
            events = store.downtime_events(conn)[-200:]
            rep = store.oee(conn, rec, since, until, [m.id for m in link.cfg.machines] or None)
            rows: list[dict[str, Any]] = sorted(
                (e.as_json() for e in events), key=lambda e: (e["ended_at"] is not None, -e["event_id"])
            )
            for m in [*rep["machines"], {"machine_id": "(cell)", **rep["cell"]}]:
                pretty = {k: _pct(m[k]) for k in ("availability", "performance", "quality", "oee")}
                rows.append({"oee": {**m, **pretty}})
            return rows

        return link.read(read)

    def fill(self, rows: list[dict[str, Any]]) -> None:
        events = [r for r in rows if "oee" not in r]
        oee = [r["oee"] for r in rows if "oee" in r]
        fill_table(self.query_one(f"#table-{self.name_}", DataTable), events, self.columns, self.key)
        fill_table(self.query_one("#table-oee", DataTable), oee, OEE_COLUMNS, "machine_id")

    def selected(self) -> dict[str, Any] | None:
        events = [r for r in self.rows if "oee" not in r]
        return selected_row(self.query_one(f"#table-{self.name_}", DataTable), events, self.key)

    def action_reason(self) -> None:
        row = self.selected()
        if not row:
            return
        event_id = int(row["event_id"])

        def picked(reason: str | None) -> None:
            if reason is not None:
                self.console.act(lambda link: give_reason(link, event_id, reason))

        self.app.push_screen(ReasonPicker(event_id, self.console.cfg.record.tree()), picked)


def give_reason(link: CellLink, event_id: int, reason: str) -> Answer:
    """DOWNTIME_RSN, as `gwc downtime reason`."""

    def go() -> str:
        assert link.bus is not None
        ack = set_downtime_reason(link.bus, reason, operator(), event_id=event_id)
        return f"{reason} ({ack.e10_state})"

    return link.act(f"downtime {event_id} reason", go)
