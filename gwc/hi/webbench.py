"""`gwc bench web`: what five open browsers on the web HMI cost a busy cell, side by side in one run.

As `gwc bench console` does for the console: `gwc bench cell`'s lots (a private cell of N dummy
machines whose runs take no time) run in rounds on one cell that has the web module, alternately with
no browser and with five headless Chromiums (Debian's, driven by Playwright) logged in and showing the
dispatch list live (the busiest page: a row changes at every step of every lot). The rounds go ABBA.
Each figure is the median over the rounds of each side: lots per second, overhead per lot, the cell's
CPU per lot (the web module's and the database's apart), database transactions and bus messages per
lot, and apart, the browsers' own CPU: theirs, not the cell's, but on this host they share its cores.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import socket
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from gwc import db
from gwc.bench import cpu_s
from gwc.bench.cell import CellBench
from gwc.client.session import context
from gwc.console.cost import BusCounter
from gwc.errors import GwcError
from gwc.soak.private_config import write_config
from gwc.users import Role, store
from gwc.users.passwords import hash_password

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
USER, PASSWORD = "bench", "bench-password"
FIGURES = [
    ("lots per second", "lots_per_s"),
    ("overhead per lot, median (ms)", "overhead_median_ms"),
    ("overhead per lot, p99 (ms)", "overhead_p99_ms"),
    ("cell CPU per lot, all its processes (ms)", "cell_cpu_ms_per_lot"),
    ("  of which the web module (ms)", "web_cpu_ms_per_lot"),
    ("  of which the database (ms)", "database_cpu_ms_per_lot"),
    ("database transactions per lot", "db_commits_per_lot"),
    ("bus messages per lot", "bus_msgs_per_lot"),
    ("the browsers' own CPU per lot (ms), not the cell's", "browsers_cpu_ms_per_lot"),
]


def browsers_cpu_s() -> float:
    """CPU seconds so far of every Chromium Playwright started (its profiles are playwright_*)."""
    total = 0.0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if b"playwright_chromium" in (d / "cmdline").read_bytes():
                total += cpu_s(int(d.name))
        except OSError:
            continue
    return total


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class WebBench(CellBench):
    """CellBench on a cell with the web module, its lots in rounds without and with browsers open."""

    counted = "xact_commit + xact_rollback"  # the web's reads end in a rollback

    def __init__(
        self,
        var: Path,
        machines: int,
        lots: int,
        pairs: int,
        browsers: int,
        log: logging.Logger,
        say: Callable[[str], None],
    ) -> None:
        super().__init__(var, machines, lots, 0, 0, os.environ.get("GWC_DATABASE_URL"), log, say, idle_s=0)
        self.pairs = pairs
        self.browsers = browsers
        self.rounds: list[dict[str, Any]] = []
        self.url = f"https://127.0.0.1:{free_port()}"
        raw = dict(self.cell.cfg.raw)
        raw["module"] = [*raw.get("module", []), {"name": "web"}]
        raw["web"] = {"listen": self.url.removeprefix("https://")}
        self.cell.cfg = dataclasses.replace(write_config(self.cell.cfg.path, raw), var=self.cell.var)

    def _lots(self) -> dict[str, Any]:
        with db.connect(self.cell.cfg, role="hi", log=self.log) as conn:
            store.add_user(conn, USER, Role.viewer, hash_password(PASSWORD), None, "bench")
        counter = BusCounter(self.cell.cfg.bus)
        try:
            for i in range(self.pairs):
                for with_web in (False, True) if i % 2 == 0 else (True, False):
                    self.rounds.append(self._round(with_web, counter))
        finally:
            counter.close()
        return {
            "machines": self.n,
            "lots": self.m,
            "browsers": self.browsers,
            "rounds": self.rounds,
            **compare(self.rounds),
        }

    def _round(self, with_web: bool, counter: BusCounter) -> dict[str, Any]:
        k = len(self.rounds) + 1
        self.say(f"round {k}: {self.m} lots " + (f"with {self.browsers} browsers open" if with_web else "with none"))
        if not with_web:
            return self._measure(False, counter)
        from playwright.sync_api import sync_playwright

        with sync_playwright() as pw:
            browsers = []
            try:
                for _ in range(self.browsers):
                    browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
                    browsers.append(browser)
                    page = browser.new_context(ignore_https_errors=True).new_page()
                    page.goto(self.url)
                    page.fill("#login-user", USER)
                    page.fill("#login-password", PASSWORD)
                    page.click("#login button[type=submit]")
                    page.wait_for_selector("#user:has-text('bench')")
                    page.click("#tabs button[data-tab=lots]")
                    page.wait_for_selector("#live:has-text('live')")
                return self._measure(True, counter)
            finally:
                for browser in browsers:
                    browser.close()

    def _measure(self, with_web: bool, counter: BusCounter) -> dict[str, Any]:
        all0, _ = counter.now()
        browsers0 = browsers_cpu_s()
        got = super()._lots()
        browsers1 = browsers_cpu_s()
        all1, _ = counter.now()
        cpu = got["loaded_cpu_ms_per_lot"]
        result = {
            "browsers": self.browsers if with_web else 0,
            "lots_per_s": got["lots_per_s"],
            "overhead_median_ms": got["loaded_overhead_ms"]["median"],
            "overhead_p99_ms": got["loaded_overhead_ms"]["p99"],
            "cell_cpu_ms_per_lot": round(sum(v for role, v in cpu.items() if not role.startswith("lot ")), 2),
            "web_cpu_ms_per_lot": cpu.get("web", 0.0),
            "database_cpu_ms_per_lot": cpu.get("database", 0.0),
            "db_commits_per_lot": got["db_commits_per_lot"],
            "bus_msgs_per_lot": round((all1 - all0) / self.m, 1),
            "browsers_cpu_ms_per_lot": round((browsers1 - browsers0) * 1000 / self.m, 2),
            "cpu_ms_per_lot_by_role": cpu,
        }
        self.say("  " + ", ".join(f"{key} {result[key]:g}" for _, key in FIGURES))
        return result


def compare(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for side, open_ in (("without", False), ("with", True)):
        mine = [r for r in rounds if bool(r["browsers"]) == open_]
        out[f"median_{side}_browsers"] = {key: statistics.median(r[key] for r in mine) for _, key in FIGURES if mine}
    return out


@click.command("web")
@click.option("--machines", type=int, default=4, show_default=True, help="Dummy machines (runs take no time).")
@click.option("--lots", type=int, default=100, show_default=True, help="Lots per round.")
@click.option("--pairs", type=int, default=2, show_default=True, help="Pairs of rounds: one without, one with.")
@click.option("--browsers", type=int, default=5, show_default=True, help="Browsers open in a round with them.")
@click.option(
    "--dir",
    "where",
    type=click.Path(file_okay=False, path_type=Path),
    help="The private cell's folder (default: var/bench-web); emptied first.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def command(machines: int, lots: int, pairs: int, browsers: int, where: Path | None, as_json: bool) -> None:
    """What open browsers on the web HMI cost a busy cell: gwc bench cell's lots in rounds on one cell
    with the web module, alternately without and with BROWSERS headless Chromiums on the dispatch list.
    Needs Debian's chromium and the playwright package (pip install playwright; no browser download)."""
    if machines < 1 or lots < 1 or pairs < 1 or browsers < 1:
        raise click.BadParameter("--machines, --lots, --pairs and --browsers must be at least 1")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        raise GwcError("gwc bench web needs the playwright package (pip install playwright)") from None
    if not Path(CHROMIUM).exists():
        raise GwcError(f"gwc bench web needs Debian's chromium at {CHROMIUM} (apt-get install chromium)")
    cfg, log = context("bench", drop=False)
    say = (lambda s: None) if as_json else click.echo
    result = WebBench(where or cfg.var / "bench-web", machines, lots, pairs, browsers, log, say).run()
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(
        f"{2 * pairs} rounds of {lots} lots on {machines} machines, alternately without and with {browsers} "
        f"browsers on the dispatch list: medians of {pairs} rounds each"
    )
    click.echo(f"{'':52s} {'no browser':>12s} {f'{browsers} browsers':>12s}")
    none, some = result["median_without_browsers"], result["median_with_browsers"]
    for label, key in FIGURES:
        click.echo(f"{label:52s} {none[key]:12.2f} {some[key]:12.2f}")
    click.echo("gwc check at the end: " + ("held" if result["check_held"] else "BROKEN"))
