"""`gwc bench console`: what one open console costs a busy cell, measured side by side in one run.

A rounds bench (gwc/hi/rounds.py: `gwc bench cell`'s lots in ABBA rounds on one cell, medians of each
side) whose load is one `gwc console` open on the cell in a real terminal (a private tmux) showing one
screen, the dispatch list by default: the busiest, a row changing at every step of every lot. Beside
the common figures: the Status Line Server's CPU per lot, the console's own conversations per lot
(its bus name is hi.console.<pid>) and the console's own CPU.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

from gwc.bench import cpu_s
from gwc.bench.cell import CellBench
from gwc.config import Config
from gwc.console.terminal import Terminal
from gwc.errors import GwcError
from gwc.hi.rounds import run_rounds

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


class ConsoleLoad:
    """One `gwc console` on the bench's cell in a real terminal (a private tmux), showing `view`: the
    load of `gwc bench console`'s rounds (gwc.hi.rounds.Load)."""

    side = "console"
    figures = FIGURES
    # Transactions, not commits alone: the console's reads end in a rollback (they write nothing).
    counted = "xact_commit + xact_rollback"
    bus_prefix = CONSOLE_NAME

    def __init__(self, view: str) -> None:
        self.view = view
        self.cfg: Config | None = None
        self.pid: int | None = None

    def attach(self, bench: CellBench) -> None:
        self.cfg = bench.cell.cfg

    def prepare(self, bench: CellBench) -> None:
        pass

    def describe(self, loaded: bool) -> str:
        return f"with a console on {self.view}" if loaded else "with no console"

    @contextlib.contextmanager
    def opened(self, k: int) -> Iterator[None]:
        """`gwc console` on the bench's cell in a terminal, on the bus and showing the view; quit with
        its own key at the round's end (a console that does not end cleanly fails the round)."""
        from gwc.console.app import ConsoleApp  # Textual only when a console is opened

        assert self.cfg is not None
        names = [name for name, _ in ConsoleApp.VIEWS]
        if self.view not in names:
            raise GwcError(f"no console screen {self.view!r}: one of {', '.join(names)}")
        # Not GWC_VAR (the cell's configuration names its var): the bench counts the cell's processes by it.
        env = {key: v for key, v in os.environ.items() if key not in ("GWC_VAR", "GWC_CONFIG")}
        env["GWC_CONFIG"] = str(self.cfg.path)
        if self.cfg.database_url:
            env["GWC_DATABASE_URL"] = self.cfg.database_url
        term = Terminal(f"gwc-bench-console-{os.getpid()}-{k}", env, "console", size=(132, 36))
        try:
            term.wait("the console to see the cell", "cell UP", timeout=OPEN_TIMEOUT)
            term.keys(str(names.index(self.view) + 1))
            self.pid = term.pid()
            yield
            term.keys("q")
            if term.exit_code(30) != 0:
                raise GwcError(f"round {k}: the console did not end cleanly:\n{term.screen()}")
        finally:
            self.pid = None
            term.close()

    def sample(self) -> float:
        return cpu_s(self.pid) if self.pid else 0.0

    def figures_of(self, loaded: bool, got: dict[str, Any], cpu_s: float, mine: int, lots: int) -> dict[str, Any]:
        return {
            "console": loaded,
            "sls_cpu_ms_per_lot": got["loaded_cpu_ms_per_lot"].get("sls", 0.0),
            "console_msgs_per_lot": round(mine / lots, 2),
            "console_cpu_ms_per_lot": round(cpu_s * 1000 / lots, 2),
            "console_cpu_percent": round(100 * cpu_s / got["seconds"], 1) if got["seconds"] else 0.0,
        }


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
    load = ConsoleLoad(view)
    run_rounds(
        load,
        where,
        "bench-console",
        machines,
        lots,
        pairs,
        as_json,
        f"a console on {view}",
        ("no console", "console"),
        44,
        view=view,
    )
