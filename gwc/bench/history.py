"""`gwc bench cell --compare-history N`: what writing the production record costs (docs/record.md).

The lots phase of `gwc bench cell` (gwc/bench/cell.py) run with cell.toml [record] history off and on,
N pairs in one sitting, each run a fresh private cell, the order alternating so that neither side
always runs first on a machine that warms up or gets busier.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from gwc.bench import brief
from gwc.client.session import bench_context

if TYPE_CHECKING:  # the bench is handed in: gwc.bench.cell imports this module when asked to compare
    from gwc.bench.cell import CellBench


def compare_history(
    bench_class: type[CellBench], where: Path, machines: int, lots: int, pairs: int, as_json: bool
) -> None:
    """`--compare-history N`: the lots phase with the production record off and on, N pairs in one
    sitting (off-on, then on-off, ...), each run a fresh private cell: lots/s and the overhead per lot
    with `machines` lots at once, side by side (docs/record.md, What it costs)."""
    _, log = bench_context()
    say = (lambda s: None) if as_json else click.echo
    runs: dict[str, list[dict[str, Any]]] = {"off": [], "on": []}
    for i in range(pairs):
        for history in (False, True) if i % 2 == 0 else (True, False):
            label = "on" if history else "off"
            say(f"pair {i + 1}: history {label}")
            bench = bench_class(
                where, machines, lots, 0, 0, os.environ.get("GWC_DATABASE_URL"), log, say, idle_s=0, history=history
            )
            r = bench.run()
            runs[label].append(
                {
                    "lots_per_s": r["lots_per_s"],
                    "failed": r["failed"],
                    "loaded_overhead_ms": r["loaded_overhead_ms"],
                    "check_held": r["check_held"],
                }
            )
    result: dict[str, Any] = {"machines": machines, "lots": lots, "pairs": pairs, "runs": runs}
    for label in ("off", "on"):
        rs = runs[label]
        result[label] = {
            "lots_per_s": sum(r["lots_per_s"] for r in rs) / len(rs),
            "overhead_median_ms": sum(r["loaded_overhead_ms"]["median"] for r in rs) / len(rs),
            "overhead_p99_ms": sum(r["loaded_overhead_ms"]["p99"] for r in rs) / len(rs),
        }
    off, on = result["off"], result["on"]
    result["on_vs_off"] = {k: on[k] / off[k] if off[k] else None for k in off}
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(f"{lots} lots on {machines} machines, {pairs} pair(s), history off | on (mean of the runs):")
    click.echo(f"  lots/s:                           {off['lots_per_s']:8.2f} | {on['lots_per_s']:8.2f}")
    for k, what in (("overhead_median_ms", "median"), ("overhead_p99_ms", "p99")):
        click.echo(f"  {machines} at once, overhead {what} (ms): {off[k]:8.2f} | {on[k]:8.2f}")
    for label in ("off", "on"):
        each = [
            f"{r['lots_per_s']:.2f} lots/s, {brief(r['loaded_overhead_ms'])} ms, check "
            + ("held" if r["check_held"] else "BROKEN")
            for r in runs[label]
        ]
        click.echo(f"  runs with history {label}: " + "; ".join(each))
