"""`gwc bench growth`: the cell from 10 to 50 to 100 machines, in one table (issue 38).

Each size is one `gwc bench cell` run (gwc/bench/cell.py, CellBench) on its own private cell, one after
the other in this invocation, so the rows compare like with like on a shared machine: lots/s, the
cell's overhead per lot with the same number of lots at work at once at every size (10 by default:
what grows with the cell is then what a lot hears, not how many lots there are), one lot at a time,
the resting cell's CPU beside its floor, and the whole cell's peak memory. The memory is the
proportional set size (PSS) of every process of the cell, the database's included, sampled twice a
second while the size runs (gwc/bench/order.py's `pss_kb`).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import click

from gwc.bench.cell import CellBench
from gwc.bench.order import database_pids, pss_kb
from gwc.client.session import bench_context

SAMPLE_S = 0.5  # how often the cell's memory is read


@dataclass
class Row:
    """One size of the cell."""

    machines: int
    lots: int
    failed: int
    lots_per_s: float
    loaded_median_ms: float  # overhead per lot, `at_once` lots at work, request to unreserve
    loaded_p99_ms: float
    growth: float  # loaded_median_ms over the first row's
    solo_median_ms: float | None  # one lot at a time
    resting_percent: float | None  # of one core, the whole cell at rest
    floor_percent: float | None  # as many bare processes waking once a heartbeat
    peak_memory_mb: float  # PSS of every process of the cell, the database included
    check_held: bool


class MemoryWatch:
    """Samples a cell's memory on a thread of its own while a size runs; `peak_mb` is the most seen."""

    def __init__(self, pids: Callable[[], set[int]]) -> None:
        self.pids = pids
        self.peak_mb = 0.0
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._watch, name="bench-memory", daemon=True)

    def _watch(self) -> None:
        while not self.done.wait(SAMPLE_S):
            try:
                self.peak_mb = max(self.peak_mb, sum(pss_kb(p) for p in self.pids()) / 1024)
            except OSError:  # a cell starting or stopping: the next sample counts
                continue

    def __enter__(self) -> MemoryWatch:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.done.set()
        self.thread.join()


def sizes(machines: str, lots: str) -> list[tuple[int, int]]:
    """`10,50,100` and `500,2000,5000` -> [(10, 500), (50, 2000), (100, 5000)]."""
    try:
        ms = [int(x) for x in machines.split(",") if x.strip()]
        ls = [int(x) for x in lots.split(",") if x.strip()]
    except ValueError as e:
        raise click.BadParameter(f"--machines and --lots are comma-separated counts: {e}") from e
    if not ms or len(ms) != len(ls) or min(ms) < 1 or min(ls) < 1:
        raise click.BadParameter("--machines and --lots: as many sizes in each, every count at least 1")
    return list(zip(ms, ls, strict=True))


def one_size(
    where: Path, machines: int, lots: int, at_once: int, solo: int, idle_s: float, log: logging.Logger
) -> dict[str, Any]:
    bench = CellBench(
        where,
        machines,
        lots,
        solo,
        0,
        os.environ.get("GWC_DATABASE_URL"),
        log,
        lambda s: None,
        idle_s=idle_s,
        at_once=at_once,
    )
    with MemoryWatch(lambda: set(bench.cell.pids()) | database_pids(bench.cell)) as watch:
        result = bench.run()
    result["peak_memory_mb"] = round(watch.peak_mb, 1)
    return result


def row_of(result: dict[str, Any], first_median: float | None) -> Row:
    loaded = result["loaded_overhead_ms"]
    return Row(
        machines=result["machines"],
        lots=result["lots"],
        failed=result["failed"],
        lots_per_s=round(result["lots_per_s"], 2),
        loaded_median_ms=round(loaded["median"], 1),
        loaded_p99_ms=round(loaded["p99"], 1),
        growth=round(loaded["median"] / first_median, 2) if first_median else 1.0,
        solo_median_ms=round(result["overhead_ms"]["median"], 1) if "overhead_ms" in result else None,
        resting_percent=result.get("idle_cpu_percent"),
        floor_percent=result.get("idle_floor_cpu_percent"),
        peak_memory_mb=result["peak_memory_mb"],
        check_held=result["check_held"],
    )


def table(rows: list[Row], at_once: int) -> str:
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}"

    lines = [
        f"machines   lots  lots/s  failed  {at_once} at once ms median (p99)  x first  one at a time ms"
        "  resting % (floor)  peak MB  gwc check",
    ]
    for r in rows:
        lines.append(
            f"{r.machines:8d} {r.lots:6d} {r.lots_per_s:7.2f} {r.failed:7d}  "
            f"{r.loaded_median_ms:12.1f} ({r.loaded_p99_ms:7.1f})  {r.growth:7.2f}  "
            f"{'-' if r.solo_median_ms is None else f'{r.solo_median_ms:.1f}':>16s}  "
            f"{pct(r.resting_percent):>8s} ({pct(r.floor_percent):>5s})  {r.peak_memory_mb:7.0f}  "
            f"{'held' if r.check_held else 'BROKEN'}"
        )
    return "\n".join(lines)


@click.command("growth")
@click.option("--machines", default="10,50,100", show_default=True, help="The cell's sizes, in machines.")
@click.option("--lots", default="500,2000,5000", show_default=True, help="Lots run at each size.")
@click.option(
    "--at-once", type=int, default=10, show_default=True, help="Lots at work at a time, the same at every size."
)
@click.option("--solo", type=int, default=50, show_default=True, help="Then lots one at a time (0: skip).")
@click.option("--idle", "idle_s", type=float, default=30.0, show_default=True, help="Seconds of rest (0: skip).")
@click.option(
    "--dir",
    "where",
    type=click.Path(file_okay=False, path_type=Path),
    help="The private cells' folder (default: var/bench-growth); emptied first.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the rows as JSON.")
def command(
    machines: str, lots: str, at_once: int, solo: int, idle_s: float, where: Path | None, as_json: bool
) -> None:
    """The cell at several sizes, one after another, in one table: lots/s, overhead per lot with the
    same lots at once, one at a time, the resting CPU beside its floor, peak memory, `gwc check`."""
    plan = sizes(machines, lots)
    if at_once < 1 or solo < 0 or idle_s < 0:
        raise click.BadParameter("--at-once at least 1, --solo and --idle at least 0")
    cfg, log = bench_context()
    base = where or cfg.var / "bench-growth"
    rows: list[Row] = []
    for n, m in plan:
        if not as_json:
            click.echo(f"{n} machines, {m} lots ...", err=True)
        result = one_size(base / f"m{n}", n, m, at_once, solo, idle_s, log)
        rows.append(row_of(result, rows[0].loaded_median_ms if rows else None))
    if as_json:
        click.echo(json.dumps({"at_once": at_once, "rows": [asdict(r) for r in rows]}, indent=1))
    else:
        click.echo(table(rows, at_once))
