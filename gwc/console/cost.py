"""`gwc bench console`: what one open console costs a busy cell, measured side by side in one run.

`gwc bench cell`'s lots (a private cell of N dummy machines whose runs take no time, one lot at a
time on each) run in rounds on one cell, alternately with no console and with one `gwc console` open
on that cell in a real terminal (a private tmux) showing one screen, the dispatch list by default:
the busiest, a row changing at every step of every lot. The rounds go ABBA (without, with, with,
without, ...), so that a drift of the shared machine's load falls on both sides alike. Each round
gives lots per second, the overhead per lot (request to unreserve, median and p99), the cell's CPU
per lot by process role (the database's included), database transactions per lot, the bus's
conversation messages per lot (a silent listener in this process counts them, the console's own
apart) and the console's own CPU. The report is each figure's median over the rounds of each side.
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from gwc.bench import cpu_s
from gwc.bench.cell import CellBench
from gwc.client.session import context
from gwc.config import BusConfig
from gwc.console.terminal import Terminal
from gwc.errors import GwcError
from gwc.hi.monitor import watch

CONSOLE_NAME = "hi.console."  # the console's bus name is hi.console.<pid> (gwc/console/link.py)
OPEN_TIMEOUT = 60.0  # the console up and showing its screen, on a loaded machine
# Figures compared, each taken from a round's result: (label, key).
FIGURES = [
    ("lots per second", "lots_per_s"),
    ("overhead per lot, median (ms)", "overhead_median_ms"),
    ("overhead per lot, p99 (ms)", "overhead_p99_ms"),
    ("cell CPU per lot, all its processes (ms)", "cell_cpu_ms_per_lot"),
    ("  of which the database (ms)", "database_cpu_ms_per_lot"),
    ("  of which the Status Line Server (ms)", "sls_cpu_ms_per_lot"),
    ("database transactions per lot", "db_commits_per_lot"),
    ("bus messages per lot", "bus_msgs_per_lot"),
    ("  of which the console's conversations", "console_msgs_per_lot"),
    ("the console's own CPU per lot (ms)", "console_cpu_ms_per_lot"),
    ("the console's own CPU (% of one core)", "console_cpu_percent"),
]


class BusCounter:
    """Conversation messages on the bus, counted by a silent listener (the monitor's): all, and those of
    the console's conversations (initiated by a console)."""

    def __init__(self, cfg: BusConfig) -> None:
        self.all = 0
        self.console = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=watch, args=(cfg, self._count, self._stop.is_set), daemon=True)
        self._thread.start()

    def _count(self, rec: dict[str, Any]) -> None:
        if "message" in rec:
            self.all += 1
            self.console += str(rec.get("initiator", "")).startswith(CONSOLE_NAME)

    def now(self) -> tuple[int, int]:
        return self.all, self.console

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


class ConsoleBench(CellBench):
    """CellBench whose lots run in rounds, alternately without and with a console open on the cell."""

    # Transactions, not commits alone: the console's reads end in a rollback (they write nothing).
    counted = "xact_commit + xact_rollback"

    def __init__(
        self,
        var: Path,
        machines: int,
        lots: int,
        pairs: int,
        view: str,
        log: logging.Logger,
        say: Callable[[str], None],
    ) -> None:
        super().__init__(var, machines, lots, 0, 0, os.environ.get("GWC_DATABASE_URL"), log, say, idle_s=0)
        self.pairs = pairs
        self.view = view
        self.rounds: list[dict[str, Any]] = []

    def _lots(self) -> dict[str, Any]:
        """CellBench's loaded lots, 2 x pairs times (its run() does the rest: start, check, stop)."""
        counter = BusCounter(self.cell.cfg.bus)
        try:
            for i in range(self.pairs):
                for with_console in (False, True) if i % 2 == 0 else (True, False):
                    self.rounds.append(self._round(with_console, counter))
        finally:
            counter.close()
        return {"machines": self.n, "lots": self.m, "view": self.view, "rounds": self.rounds, **compare(self.rounds)}

    def _round(self, with_console: bool, counter: BusCounter) -> dict[str, Any]:
        k = len(self.rounds) + 1
        self.say(f"round {k}: {self.m} lots {'with a console on ' + self.view if with_console else 'with no console'}")
        term = self._open_console(k) if with_console else None
        try:
            pid = term.pid() if term is not None else None
            cpu0, (all0, console0) = (cpu_s(pid) if pid else 0.0), counter.now()
            got = super()._lots()
            cpu1, (all1, console1) = (cpu_s(pid) if pid else 0.0), counter.now()
            if term is not None:
                term.keys("q")
                if term.exit_code(30) != 0:
                    raise GwcError(f"round {k}: the console did not end cleanly:\n{term.screen()}")
        finally:
            if term is not None:
                term.close()
        cpu = got["loaded_cpu_ms_per_lot"]
        result = {
            "console": with_console,
            "lots_per_s": got["lots_per_s"],
            "overhead_median_ms": got["loaded_overhead_ms"]["median"],
            "overhead_p99_ms": got["loaded_overhead_ms"]["p99"],
            "cell_cpu_ms_per_lot": round(sum(v for role, v in cpu.items() if not role.startswith("lot ")), 2),
            "database_cpu_ms_per_lot": cpu.get("database", 0.0),
            "sls_cpu_ms_per_lot": cpu.get("sls", 0.0),
            "db_commits_per_lot": got["db_commits_per_lot"],
            "bus_msgs_per_lot": round((all1 - all0) / self.m, 1),
            "console_msgs_per_lot": round((console1 - console0) / self.m, 2),
            "console_cpu_ms_per_lot": round((cpu1 - cpu0) * 1000 / self.m, 2),
            "console_cpu_percent": round(100 * (cpu1 - cpu0) / got["seconds"], 1) if got["seconds"] else 0.0,
            "cpu_ms_per_lot_by_role": cpu,
        }
        self.say("  " + ", ".join(f"{key} {result[key]:g}" for _, key in FIGURES))
        return result

    def _open_console(self, k: int) -> Terminal:
        """`gwc console` on the bench's cell in a terminal, on the bus and showing self.view."""
        from gwc.console.app import ConsoleApp  # Textual only when a console is opened

        names = [name for name, _ in ConsoleApp.VIEWS]
        if self.view not in names:
            raise GwcError(f"no console screen {self.view!r}: one of {', '.join(names)}")
        # Not GWC_VAR (the cell's configuration names its var): the bench counts the cell's processes by it.
        env = {key: v for key, v in os.environ.items() if key not in ("GWC_VAR", "GWC_CONFIG")}
        env["GWC_CONFIG"] = str(self.cell.cfg.path)
        if self.cell.cfg.database_url:
            env["GWC_DATABASE_URL"] = self.cell.cfg.database_url
        term = Terminal(f"gwc-bench-console-{os.getpid()}-{k}", env, "console", size=(132, 36))
        try:
            term.wait("the console to see the cell", "cell UP", timeout=OPEN_TIMEOUT)
            term.keys(str(names.index(self.view) + 1))
        except GwcError:
            term.close()
            raise
        return term


def compare(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Each figure's median over the rounds without a console and over those with one."""
    out: dict[str, Any] = {}
    for side, with_console in (("without", False), ("with", True)):
        mine = [r for r in rounds if r["console"] == with_console]
        out[f"median_{side}_console"] = {key: statistics.median(r[key] for r in mine) for _, key in FIGURES if mine}
    return out


@click.command("console")
@click.option("--machines", type=int, default=4, show_default=True, help="Dummy machines (runs take no time).")
@click.option("--lots", type=int, default=100, show_default=True, help="Lots per round.")
@click.option("--pairs", type=int, default=3, show_default=True, help="Pairs of rounds: one without, one with.")
@click.option("--view", default="lots", show_default=True, help="The console's screen while it runs (lots: DISP).")
@click.option(
    "--dir",
    "where",
    type=click.Path(file_okay=False, path_type=Path),
    help="The private cell's folder (default: var/bench-console); emptied first.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def command(machines: int, lots: int, pairs: int, view: str, where: Path | None, as_json: bool) -> None:
    """What an open `gwc console` costs a busy cell: gwc bench cell's lots in rounds on one cell,
    alternately without and with a console on it (in tmux), medians of each side. Needs tmux."""
    if machines < 1 or lots < 1 or pairs < 1:
        raise click.BadParameter("--machines, --lots and --pairs must be at least 1")
    cfg, log = context("bench", drop=False)
    say = (lambda s: None) if as_json else click.echo
    result = ConsoleBench(where or cfg.var / "bench-console", machines, lots, pairs, view, log, say).run()
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(
        f"{2 * pairs} rounds of {lots} lots on {machines} machines, alternately without and with a console "
        f"on {view}: medians of {pairs} rounds each"
    )
    click.echo(f"{'':44s} {'no console':>12s} {'console':>12s}")
    none, one = result["median_without_console"], result["median_with_console"]
    for label, key in FIGURES:
        click.echo(f"{label:44s} {none[key]:12.2f} {one[key]:12.2f}")
    click.echo("gwc check at the end: " + ("held" if result["check_held"] else "BROKEN"))
