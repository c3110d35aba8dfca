"""The Human Interface: the operator's commands, one module per group of the thesis's screens.

The commands parse their arguments and print; what they do with the cell is gwc.client's.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import click

from gwc.client.session import bench_context, context

__all__ = ["bench_context", "context", "json_option", "table"]


def table(rows: Sequence[dict[str, Any]], columns: Sequence[str], as_json: bool = False) -> None:
    """Print rows as an aligned table for a person, or as a JSON list for scripts."""
    if as_json:
        click.echo(json.dumps(list(rows), default=str, indent=1))
        return
    if not rows:
        click.echo("(none)")
        return
    cells = [[("" if r.get(c) is None else str(r.get(c))) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    click.echo("  ".join(c.upper().ljust(w) for c, w in zip(columns, widths)).rstrip())
    for row in cells:
        click.echo("  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip())


json_option = click.option("--json", "as_json", is_flag=True, help="Print JSON for scripts instead of a table.")
