"""`gwc soak`: run a private cell under seeded chaos and say whether it kept its promises."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import click

from gwc.hi import bench_context
from gwc.soak.driver import SoakOptions, read_header, run_soak
from gwc.soak.plan import ACTION_WEIGHTS


@click.command("soak")
@click.option("--minutes", type=float, default=2.0, show_default=True, help="How long lots and faults keep coming.")
@click.option("--seed", type=int, default=1, show_default=True, help="Seed of the lots and the faults.")
@click.option("--machines", type=int, default=6, show_default=True, help="Dummy machines in the private cell.")
@click.option(
    "--only",
    "kinds",
    multiple=True,
    type=click.Choice(sorted(ACTION_WEIGHTS)),
    help="Only these fault kinds (repeatable; default: all).",
)
@click.option(
    "--replay",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Run again the scenario recorded in this actions.jsonl (its seed and options).",
)
@click.option(
    "--dir",
    "where",
    type=click.Path(file_okay=False, path_type=Path),
    help="The soak's folder (default: var/soak): actions.jsonl, report.json, the private cell.",
)
@click.option(
    "--agent/--no-agent",
    default=True,
    show_default=True,
    help="The host's agent restarts what is killed (--no-agent: the driver restarts it, as a cell without one).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def soak(
    minutes: float,
    seed: int,
    machines: int,
    kinds: tuple[str, ...],
    replay: Path | None,
    where: Path | None,
    agent: bool,
    as_json: bool,
) -> None:
    """Run lots through a private cell of MSCHED, the servers and dummy machines while a seeded
    driver kill -9s WCs, MEs, machine pairs, MSCHED and the servers, stops machines through the HI
    and turns on the bus fault injector. Exit 0 only when every lot finished or failed with a
    reason, none was lost or run twice, `gwc check` holds and nothing was left behind.

    The private cell uses $GWC_DATABASE_URL if set (it should be an empty cell database), otherwise
    an embedded cluster of its own under the soak's folder. Every fault is logged with its time in
    actions.jsonl; the same seed gives the same faults in the same order.
    """
    cfg, log = bench_context("soak")
    options: dict[str, Any] = dict(seed=seed, minutes=minutes, machines=machines, kinds=tuple(kinds), agent=agent)
    if replay is not None:
        h = read_header(replay)
        options = dict(
            seed=h["seed"],
            minutes=h["minutes"],
            machines=h["machines"],
            kinds=tuple(h["kinds"]),
            run_time=h["run_time"],
            lot_every=h["lot_every"],
            action_every=tuple(h["action_every"]),
            max_active=h["max_active"],
            script_path=h["script_path"],
            agent=h.get("agent", False),
        )
        click.echo(f"replaying {replay}: seed {h['seed']}, {h['minutes']:g} min")
    opts = SoakOptions(var=(where or cfg.var / "soak"), database_url=os.environ.get("GWC_DATABASE_URL"), **options)
    if replay is not None and replay.resolve() == (opts.var / "actions.jsonl").resolve():
        kept = opts.var / "actions.recorded.jsonl"  # this run writes actions.jsonl anew: keep the recording
        shutil.copyfile(replay, kept)
        click.echo(f"the recording is kept as {kept}")
    report = run_soak(opts, log, say=(lambda s: None) if as_json else click.echo)
    if as_json:
        click.echo(json.dumps(report.as_dict(), indent=1, default=str))
    else:
        for line in report.summary():
            click.echo(line)
        click.echo(f"actions: {opts.var / 'actions.jsonl'}; report: {opts.var / 'report.json'}")
    if not report.clean:
        raise click.exceptions.Exit(1)


commands = [soak]
