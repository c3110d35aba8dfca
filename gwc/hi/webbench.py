"""`gwc bench web`: what five open browsers on the web HMI cost a busy cell, side by side in one run.

A rounds bench (gwc/hi/rounds.py: `gwc bench cell`'s lots in ABBA rounds on one cell, medians of each
side), as `gwc bench console` is, on a cell that has the web module; its load is five headless
Chromiums (Debian's, driven by Playwright) logged in and showing the dispatch list live (the busiest
page: a row changes at every step of every lot). Beside the common figures: the web module's CPU per
lot, and apart, the browsers' own CPU: theirs, not the cell's, but on this host they share its cores.
"""

from __future__ import annotations

import contextlib
import dataclasses
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

from gwc import db
from gwc.bench import cpu_s
from gwc.bench.cell import CellBench
from gwc.errors import GwcError
from gwc.hi.rounds import run_rounds
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


class WebLoad:
    """Headless Chromiums logged in to the cell's web HMI, each on the dispatch list live: the load of
    `gwc bench web`'s rounds (gwc.hi.rounds.Load). The bench's cell gets the web module."""

    side = "browsers"
    figures = FIGURES
    counted = "xact_commit + xact_rollback"  # the web's reads end in a rollback
    bus_prefix = "\0"  # the web module's conversations are the cell's: none counted apart

    def __init__(self, browsers: int) -> None:
        self.browsers = browsers
        self.url = f"https://127.0.0.1:{free_port()}"

    def attach(self, bench: CellBench) -> None:
        raw = dict(bench.cell.cfg.raw)
        raw["module"] = [*raw.get("module", []), {"name": "web"}]
        raw["web"] = {"listen": self.url.removeprefix("https://")}
        bench.cell.cfg = dataclasses.replace(write_config(bench.cell.cfg.path, raw), var=bench.cell.var)

    def prepare(self, bench: CellBench) -> None:
        with db.connect(bench.cell.cfg, role="hi", log=bench.log) as conn:
            store.add_user(conn, USER, Role.viewer, hash_password(PASSWORD), None, "bench")

    def describe(self, loaded: bool) -> str:
        return f"with {self.browsers} browsers open" if loaded else "with none"

    @contextlib.contextmanager
    def opened(self, k: int) -> Iterator[None]:
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
                yield
            finally:
                for browser in browsers:
                    browser.close()

    def sample(self) -> float:
        return browsers_cpu_s()

    def figures_of(self, loaded: bool, got: dict[str, Any], cpu_s: float, mine: int, lots: int) -> dict[str, Any]:
        return {
            "browsers": self.browsers if loaded else 0,
            "web_cpu_ms_per_lot": got["loaded_cpu_ms_per_lot"].get("web", 0.0),
            "browsers_cpu_ms_per_lot": round(cpu_s * 1000 / lots, 2),
        }


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
    load = WebLoad(browsers)
    columns = ("no browser", f"{browsers} browsers")
    what = f"{browsers} browsers on the dispatch list"
    run_rounds(load, where, "bench-web", machines, lots, pairs, as_json, what, columns, 52, browsers=browsers)
