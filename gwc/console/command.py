"""`gwc console`: the click command. Textual is imported only when the console runs, so that every
other `gwc` command starts as fast as before."""

from __future__ import annotations

from pathlib import Path

import click

from gwc.config import load_config
from gwc.console.link import console_log


@click.command("console")
@click.option(
    "--screenshots",
    type=click.Path(file_okay=False, path_type=Path),
    help="Save each view as an SVG in this folder (console-VIEW.svg, 132x36), then quit (for docs/).",
)
def console(screenshots: Path | None) -> None:
    """The operator's console: the HI's screens live in the terminal (MSTT, DISP, WOEN, WOSU, MREQ,
    alarms, STRT, the monitor), the status line always shown. Keys 1-8 switch screens, q quits."""
    from gwc.console.app import ConsoleApp, screenshot_every_view

    cfg = load_config()
    app = ConsoleApp(cfg, console_log(cfg))
    if screenshots is None:
        app.run()
        if app.return_code:
            raise SystemExit(app.return_code)
        return
    screenshots.mkdir(parents=True, exist_ok=True)
    app.run(headless=True, size=(132, 36), auto_pilot=screenshot_every_view(screenshots))
    click.echo(f"saved {len(app.VIEWS)} views in {screenshots}")


commands = [console]
