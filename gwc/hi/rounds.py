"""A rounds bench: what something open on a busy cell costs it, measured side by side in one run.

`gwc bench cell`'s lots (a private cell of N dummy machines whose runs take no time, one lot at a
time on each) run in rounds on one cell, alternately without and with a load open on it (`gwc bench
console`: one console in a terminal; `gwc bench web`: headless browsers on the web HMI). The rounds
go ABBA (without, with, with, without, ...), so that a drift of the shared machine's load falls on
both sides alike. Each round gives lots per second, the overhead per lot (request to unreserve,
median and p99), the cell's CPU per lot (the database's apart), database transactions and bus
conversation messages per lot (a silent listener in this process counts them), and the load's own
figures. The report is each figure's median over the rounds of each side.

The bench is one object; what it opens is a part it holds, a `Load`, with a small interface.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import statistics
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import click

from gwc.bench.cell import CellBench
from gwc.client.session import bench_context
from gwc.config import BusConfig
from gwc.hi.monitor import watch

Figures = list[tuple[str, str]]  # (label, key of a round's result), in the order reported


class BusCounter:
    """Conversation messages on the bus, counted by a silent listener (the monitor's): all, and those of
    conversations initiated by a module whose name starts with `mine` (a console's, hi.console.<pid>)."""

    def __init__(self, cfg: BusConfig, mine: str = "\0") -> None:
        self.all = 0
        self.mine = 0
        self.prefix = mine
        self._stop = threading.Event()
        self._thread = threading.Thread(target=watch, args=(cfg, self._count, self._stop.is_set), daemon=True)
        self._thread.start()

    def _count(self, rec: dict[str, Any]) -> None:
        if "message" in rec:
            self.all += 1
            self.mine += str(rec.get("initiator", "")).startswith(self.prefix)

    def now(self) -> tuple[int, int]:
        return self.all, self.mine

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


class Load(Protocol):
    """What a rounds bench opens on the cell in half its rounds."""

    side: str  # its name in the results: a round's flag, and median_without_<side> / median_with_<side>
    figures: Figures  # every figure reported, the common ones among them
    counted: str  # pg_stat_database's transaction counters the bench adds up (CellBench.counted)
    bus_prefix: str  # the bus name its own conversations start with ("\0": none counted apart)

    def attach(self, bench: CellBench) -> None:
        """The bench's private cell made, not started: change its configuration if the load needs to."""

    def prepare(self, bench: CellBench) -> None:
        """The cell started, before the first round."""

    def describe(self, loaded: bool) -> str:
        """What a round runs with, for the progress line: "with a console on lots"."""
        ...

    def opened(self, k: int) -> contextlib.AbstractContextManager[None]:
        """The load open for round `k` (closed when the round ends)."""
        ...

    def sample(self) -> float:
        """The load's own CPU seconds so far (0 when it keeps none)."""
        ...

    def figures_of(self, loaded: bool, got: dict[str, Any], cpu_s: float, mine: int, lots: int) -> dict[str, Any]:
        """The load's own figures of a round: from CellBench's result `got`, the load's CPU seconds and
        its own bus messages over the round, for `lots` lots."""
        ...


class RoundsBench(CellBench):
    """CellBench whose lots run in rounds, alternately without and with `load` open on the cell."""

    def __init__(
        self,
        var: Path,
        machines: int,
        lots: int,
        pairs: int,
        load: Load,
        log: logging.Logger,
        say: Callable[[str], None],
    ) -> None:
        super().__init__(var, machines, lots, 0, 0, os.environ.get("GWC_DATABASE_URL"), log, say, idle_s=0)
        self.counted = load.counted
        self.pairs = pairs
        self.load = load
        self.rounds: list[dict[str, Any]] = []
        load.attach(self)

    def _lots(self) -> dict[str, Any]:
        """CellBench's loaded lots, 2 x pairs times (its run() does the rest: start, check, stop)."""
        self.load.prepare(self)
        counter = BusCounter(self.cell.cfg.bus, self.load.bus_prefix)
        try:
            for i in range(self.pairs):
                for loaded in (False, True) if i % 2 == 0 else (True, False):
                    self.rounds.append(self._round(loaded, counter))
        finally:
            counter.close()
        return {"machines": self.n, "lots": self.m, "rounds": self.rounds, **compare(self.rounds, self.load)}

    def _round(self, loaded: bool, counter: BusCounter) -> dict[str, Any]:
        k = len(self.rounds) + 1
        self.say(f"round {k}: {self.m} lots {self.load.describe(loaded)}")
        with self.load.opened(k) if loaded else contextlib.nullcontext():
            cpu0, (all0, mine0) = self.load.sample(), counter.now()
            got = super()._lots()
            cpu1, (all1, mine1) = self.load.sample(), counter.now()
        cpu = got["loaded_cpu_ms_per_lot"]
        result = {
            "lots_per_s": got["lots_per_s"],
            "overhead_median_ms": got["loaded_overhead_ms"]["median"],
            "overhead_p99_ms": got["loaded_overhead_ms"]["p99"],
            "cell_cpu_ms_per_lot": round(sum(v for role, v in cpu.items() if not role.startswith("lot ")), 2),
            "database_cpu_ms_per_lot": cpu.get("database", 0.0),
            "db_commits_per_lot": got["db_commits_per_lot"],
            "bus_msgs_per_lot": round((all1 - all0) / self.m, 1),
            **self.load.figures_of(loaded, got, cpu1 - cpu0, mine1 - mine0, self.m),
            "cpu_ms_per_lot_by_role": cpu,
        }
        self.say("  " + ", ".join(f"{key} {result[key]:g}" for _, key in self.load.figures))
        return result


def compare(rounds: list[dict[str, Any]], load: Load) -> dict[str, Any]:
    """Each figure's median over the rounds without the load and over those with it."""
    out: dict[str, Any] = {}
    for side, loaded in (("without", False), ("with", True)):
        mine = [r for r in rounds if bool(r[load.side]) == loaded]
        out[f"median_{side}_{load.side}"] = {
            key: statistics.median(r[key] for r in mine) for _, key in load.figures if mine
        }
    return out


def run_rounds(
    load: Load,
    where: Path | None,
    folder: str,
    machines: int,
    lots: int,
    pairs: int,
    as_json: bool,
    what: str,
    columns: tuple[str, str],
    width: int,
    **extra: Any,
) -> None:
    """A bench command's body: the rounds on a private cell in `where` (default: var/<folder>), then
    the JSON (with `extra`) or the table of the two sides' medians (`what` the load is, for the title)."""
    cfg, log = bench_context()
    say: Callable[[str], None] = (lambda s: None) if as_json else click.echo
    result = RoundsBench(where or cfg.var / folder, machines, lots, pairs, load, log, say).run()
    if as_json:
        click.echo(json.dumps({**result, **extra}, indent=1))
        return
    click.echo(
        f"{2 * pairs} rounds of {lots} lots on {machines} machines, alternately without and with {what}: "
        f"medians of {pairs} rounds each"
    )
    click.echo(f"{'':{width}s} {columns[0]:>12s} {columns[1]:>12s}")
    without, with_ = result[f"median_without_{load.side}"], result[f"median_with_{load.side}"]
    for label, key in load.figures:
        click.echo(f"{label:{width}s} {without[key]:12.2f} {with_[key]:12.2f}")
    click.echo("gwc check at the end: " + ("held" if result["check_held"] else "BROKEN"))
