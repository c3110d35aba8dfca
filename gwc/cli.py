"""The `gwc` command: the Human Interface and the cell's tools, one click group.

Every command turns a GwcError into one line on stderr and the error's exit code: never a traceback.
Command groups live in gwc/hi/ and are added here, so this file stays an index.
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import Any

import click

from gwc.errors import GwcError

# Each module exposes `commands`, a list of click commands added to the top-level group.
COMMAND_MODULES = [
    "gwc.hi.cell",  # db, start, stop, status, run (STRT)
    "gwc.hi.machine",  # machine start/stop/status (MSTT)
    "gwc.hi.requests",  # machine requests and cancel (MREQ, Listing 8)
    "gwc.hi.orders",  # work orders (WOEN, WOSU), dispatch list, import/export (DISP, IMPL), lots
    "gwc.hi.lots",  # lots divide/merge/destroy (1.4.4), around the dispatch list: after gwc.hi.orders
    "gwc.hi.alarm",  # alarms and their clearing, the status line
    "gwc.hi.recipe",  # the recipe library (ERS)
    "gwc.hi.monitor",  # the conversation monitor
    "gwc.console.command",  # the operator's console (all the screens above, live)
    "gwc.hi.key",  # the cell's keys
    "gwc.hi.check",  # cell invariants
    "gwc.hi.soak",  # the chaos soak
    "gwc.hi.demo",  # section 7's demonstration
    "gwc.hi.bench",  # benchmarks
    "gwc.hi.record",  # the production record: report oee/html, trace, downtime
    "gwc.hi.dbcluster",  # gwc db cluster, gwc db switchover: the database under Patroni
]


class GwcGroup(click.Group):
    """A group that reports GwcError as one line and its exit code."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except GwcError as e:
            click.echo(f"gwc: {e}", err=True)
            ctx.exit(e.exit_code)
        except KeyboardInterrupt:
            click.echo("gwc: interrupted", err=True)
            ctx.exit(130)


@click.group(cls=GwcGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="gwc")
@click.option("--host", metavar="NAME", help="Which of the cell's [[host]]s this is (else $GWC_HOST, else found).")
def cli(host: str | None) -> None:
    """GWC, the Generic WorkCell: run and operate a factory cell.

    Configuration is etc/cell.toml (or $GWC_CONFIG); state is var/ (or $GWC_VAR); the database is
    the embedded PostgreSQL cluster under var/pg unless $GWC_DATABASE_URL names another.
    """
    if host:  # through the environment, so the modules `gwc start` spawns know it too
        os.environ["GWC_HOST"] = host


# The processes the agent spawns at every (re)start load only their own commands: the console, the
# benches and OPC UA cost a new process 0.55 s of CPU more to import, seconds of a restart on a loaded
# machine (docs/reliability.md, *How long detection takes*).
PROCESS_COMMANDS = {"run": "gwc.hi.cell", "agent": "gwc.hi.cell"}


def command_modules(argv: list[str]) -> list[str]:
    """The command modules to load for this command line: all of them, but for `gwc run` and `gwc agent`."""
    fast = PROCESS_COMMANDS.get(argv[1]) if len(argv) > 1 else None
    return [fast] if fast else COMMAND_MODULES


for _name in command_modules(sys.argv):
    for _cmd in importlib.import_module(_name).commands:
        cli.add_command(_cmd)


def main() -> None:
    sys.exit(cli.main(prog_name="gwc", standalone_mode=True))
