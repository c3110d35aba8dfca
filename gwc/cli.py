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

# Each command's module, which exposes `commands`, a list of click commands. A command line loads
# only the module of its own command: a new `gwc` process imports 0.2 s (the benches, OPC UA and the
# console) to 0.9 s of CPU less, seconds of a test suite that runs `gwc` hundreds of times, and of an
# agent's restart on a loaded machine (docs/reliability.md, *How long detection takes*). `gwc --help`
# loads them all. tests/unit/test_cli.py checks this table against the modules.
COMMANDS = {
    **dict.fromkeys(["start", "stop", "status", "restart", "agent", "run"], "gwc.hi.cell"),  # STRT
    "db": "gwc.hi.dbcluster",  # the database: gwc.hi.cell's db group, with cluster and switchover (Patroni)
    "machine": "gwc.hi.machine",  # MSTT
    **dict.fromkeys(["requests", "cancel", "unreserve"], "gwc.hi.requests"),  # MREQ, Listing 8
    # work orders (WOEN, WOSU), import/export (IMPL) and the masters
    **dict.fromkeys(["order", "import", "export", "release", "customer", "product", "script"], "gwc.hi.orders"),
    "lots": "gwc.hi.lots",  # the dispatch list (DISP) and lots divide/merge/destroy (1.4.4)
    **dict.fromkeys(["alarm", "status-line"], "gwc.hi.alarm"),  # alarms, their clearing, the status line
    "recipe": "gwc.hi.recipe",  # the recipe library (ERS)
    "monitor": "gwc.hi.monitor",  # the conversation monitor
    "console": "gwc.console.command",  # the operator's console (all the screens above, live)
    "key": "gwc.hi.key",  # the cell's keys
    "host": "gwc.hi.host",  # the host's OS users for the cell and its lot scripts
    "check": "gwc.hi.check",  # cell invariants
    "soak": "gwc.hi.soak",  # the chaos soak
    "demo": "gwc.hi.demo",  # section 7's demonstration
    "bench": "gwc.hi.bench",  # benchmarks
    **dict.fromkeys(["report", "trace", "downtime"], "gwc.hi.record"),  # the production record
    **dict.fromkeys(["spc", "tool"], "gwc.hi.quality"),  # quality: control charts, tool changes (docs/quality.md)
    "user": "gwc.hi.user",  # the cell's users and their roles
    "audit": "gwc.hi.audit",  # the audit trail
    "upgrade": "gwc.hi.upgrade",  # rolling upgrades: versions, the standby-first handover (issue 36)
}

# The commands of which some act on the cell: only their lines load the door (gwc/hi/door.py,
# COMMAND_ACTIONS: tests/unit/test_users.py checks the two agree).
ACTING = frozenset(
    {"machine", "alarm", "order", "customer", "import", "export", "release", "lots", "cancel", "unreserve"}
    | {"recipe", "script", "downtime", "tool"}
)


class GwcGroup(click.Group):
    """A group that reports GwcError as one line and its exit code, and loads a command's module only
    when the command is asked for (click's lazy group)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        module = COMMANDS.get(cmd_name)
        if module is None:
            return None
        return {c.name: c for c in importlib.import_module(module).commands}.get(cmd_name)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            words = [*getattr(ctx, "_protected_args", []), *ctx.args]
            if ctx.parent is not None or not words or words[0] not in ACTING:
                return super().invoke(ctx)  # nothing the role table names: no import of the door
            from gwc.hi.door import gwc_door  # the role table and the audit trail (docs/users.md)

            with gwc_door(words):
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


def main() -> None:
    sys.exit(cli.main(prog_name="gwc", standalone_mode=True))
