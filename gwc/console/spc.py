"""The console's SPC screen (docs/quality.md): one row per control chart (machine, recipe, feature) with
its limits, Cp, Cpk, parts out of tolerance and the rules broken; under it the highlighted chart drawn,
as `gwc spc` draws it. Read again when a run completes (a part measured)."""

from __future__ import annotations

from typing import Any

import psycopg
from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.widgets import DataTable, Static

from gwc.console.link import CellLink
from gwc.console.views import View, fill_table, selected_row
from gwc.quality.charts import charts


def _f(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


class SpcView(View):
    name_ = "spc"
    columns = ("chart", "points", "cl", "ucl", "lcl", "cp", "cpk", "out_of_tolerance", "rules")
    key = "chart"
    help = "Control charts of the measured features (individuals; Western Electric rules); the highlighted one below"

    def compose(self) -> ComposeResult:
        yield from super().compose()
        yield Static(Text(""), id="spc-drawing")

    def fetch(self, link: CellLink) -> list[dict[str, Any]] | None:
        cfg = link.cfg

        def read(conn: psycopg.Connection[Any]) -> list[dict[str, Any]]:
            def rows(sql: str, params: Any = ()) -> list[tuple[Any, ...]]:
                return list(conn.execute(sql, tuple(params)).fetchall())

            return [
                {
                    "chart": f"{c['machine_id']} {c['recipe_id']} {c['feature']}",
                    "points": c["points"],
                    "cl": _f(c["center"], ".4f"),
                    "ucl": _f(c["ucl"], ".4f"),
                    "lcl": _f(c["lcl"], ".4f"),
                    "cp": _f(c["cp"], ".2f"),
                    "cpk": _f(c["cpk"], ".2f"),
                    "out_of_tolerance": c["out_of_tolerance"],
                    "rules": ", ".join(sorted({v["rule"] for v in c["violations"]})) or "-",
                    "drawing": "\n".join(c["drawing"]),
                }
                for c in charts(rows, cfg, None, None)
            ]

        return link.read(read)

    def fill(self, rows: list[dict[str, Any]]) -> None:
        fill_table(self.query_one(f"#table-{self.name_}", DataTable), rows, self.columns, self.key)
        self._draw()

    def _draw(self) -> None:
        row = selected_row(self.query_one(f"#table-{self.name_}", DataTable), self.rows, self.key)
        row = row or (self.rows[0] if self.rows else None)
        text = f"{row['chart']}\n{row['drawing']}" if row else "(no measured features: docs/quality.md)"
        self.query_one("#spc-drawing", Static).update(Text(text))

    @on(DataTable.RowHighlighted)
    def highlighted(self, event: DataTable.RowHighlighted) -> None:
        self._draw()
