"""`gwc console`: the click command. Textual is imported only when the console runs, so that every
other `gwc` command starts as fast as before."""

from __future__ import annotations

import click

from gwc.hi import context


@click.command("console")
def console() -> None:
    """The operator's console: the HI's screens live in the terminal (MSTT, DISP, WOEN, WOSU, MREQ,
    alarms, STRT, the monitor), the status line always shown. Keys 1-8 switch screens, q quits."""
    from gwc.console.app import ConsoleApp

    cfg, log = context()
    ConsoleApp(cfg, log).run()


commands = [console]
