"""The `gwc` command's index (gwc/cli.py): every command is found in the module the table names, and a
command line loads only its own command's module."""

from __future__ import annotations

import importlib
import subprocess
import sys

from click.testing import CliRunner

from gwc.cli import COMMANDS, cli


def test_the_table_names_every_command_of_every_module_and_only_those() -> None:
    for module in sorted(set(COMMANDS.values())):
        defined = {c.name for c in importlib.import_module(module).commands}
        listed = {name for name, m in COMMANDS.items() if m == module}
        # Two groups are extended by a later module, which the table names: gwc.hi.lots adds divide/merge/
        # destroy to gwc.hi.orders' dispatch list, gwc.hi.dbcluster adds cluster/switchover to gwc.hi.cell's db.
        assert listed <= defined, f"{module} lacks {listed - defined}"
        assert defined - listed <= {"lots", "db"}, f"{module} defines {defined - listed}, not in gwc/cli.py's COMMANDS"


def test_help_lists_every_command_and_an_unknown_one_is_refused() -> None:
    out = CliRunner().invoke(cli, ["--help"]).output
    assert all(name in out for name in COMMANDS)
    bad = CliRunner().invoke(cli, ["no-such-command"])
    assert bad.exit_code == 2 and "No such command 'no-such-command'" in bad.output


def test_a_command_line_loads_only_its_own_commands_module() -> None:
    probe = "import sys; sys.argv = ['gwc', 'status', '--help']; import gwc.cli as c\n"
    probe += "try:\n    c.main()\nexcept SystemExit:\n    pass\n"
    probe += "print(sorted(m for m in sys.modules if m.startswith(('gwc.hi.', 'gwc.console', 'gwc.opcua', 'asyncua'))))"
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60).stdout
    assert loaded.strip().splitlines()[-1] == "['gwc.hi.cell']"
