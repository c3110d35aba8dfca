"""`gwc bench quality`: the same simulated tool wear run twice in one private cell, feedback off and on.

The cell: the Mazak (a dummy mill with a process: bias, tool wear, noise; gwc/quality/process.py), a
second mill wc2 without wear, and the CMM simulator measuring each part's features. Each part is a
lot of the shipped mill_and_measure script (re-milled when out of tolerance, scrap after three
millings), at most --at-once lots at a time, the bench being the operator (imports, exports).

1. without: the mill's recipe has FEATUREs only; N parts on the Mazak.
2. with: the tool changed (wear from zero, as in 1), the recipe's new version adds FEEDBACK; N parts.
3. shift: the Mazak shut down, wc2 (no wear) makes SHIFT_AFTER parts, then its DIAMETER moves by 2 sigma
   (an injected step shift); counted: parts from the shift to the first SPC_RULE alarm on wc2.

Side by side: parts out of tolerance at their first measurement, re-millings, scrap, Cpk per feature.
The JSON shape is fixed (docs/quality.md) so that other tools can rely on it.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import click
import psycopg

from gwc import db
from gwc.cell import shutdown, startup
from gwc.client.orders import decide
from gwc.client.recipes import approve_recipe, store_recipe
from gwc.client.session import bench_context
from gwc.errors import GwcError, ModuleError
from gwc.ipc.codes import LotState
from gwc.ipc.names import Conv
from gwc.lot.entity import create_lot
from gwc.lot.run import spawn_lot_script
from gwc.quality import spc
from gwc.retry import Deadline
from gwc.soak.cell import PrivateCell

FEATURES = {"DIAMETER": (25.0, 0.05), "HEIGHT": (40.0, 0.10)}
SIGMA = {"DIAMETER": 0.006, "HEIGHT": 0.012}
WEAR = {"DIAMETER": 0.0003, "HEIGHT": 0.0004}  # per part cut since the tool change
BIAS = {"DIAMETER": 0.012, "HEIGHT": 0.01}
FEEDBACK = "FEEDBACK EWMA 0.3 STEP 0.02 LIMIT 0.15"
SHIFT_AFTER = 20  # wc2's parts before its step shift (SPC's limits come from the first 20)
SHIFT_PARTS = 15  # parts after the shift at most
PHASE_TIMEOUT = 1800.0


def feature_lines() -> str:
    return "".join(f"FEATURE {f} {n:.2f} {t:.2f}\n" for f, (n, t) in FEATURES.items())


def machines(seed: int) -> list[dict[str, Any]]:
    return [
        {
            "id": "mazak",
            "kind": "dummy",
            "run_time": 0.02,
            "process": {"seed": seed, "bias": BIAS, "wear": WEAR, "sigma": SIGMA},
        },
        {
            "id": "wc2",
            "kind": "dummy",
            "run_time": 0.02,
            "process": {
                "seed": seed + 1,
                "sigma": SIGMA,
                "shift": {"after": SHIFT_AFTER, "DIAMETER": 2 * SIGMA["DIAMETER"]},
            },
        },
        {
            "id": "cmm_wc",
            "kind": "cmm",
            "homing_alarm": False,
            "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0},
            "sim": {"measure_time": 0.02, "gauge_sigma": 0.0005, "seed": seed},
        },
    ]


class QualityBench:
    def __init__(
        self,
        var: Path,
        parts: int,
        seed: int,
        at_once: int,
        database_url: str | None,
        log: logging.Logger,
        say: Callable[[str], None],
    ) -> None:
        self.var = var.resolve()
        self.parts, self.seed, self.at_once = parts, seed, at_once
        self.log, self.say = log, say
        if self.var.exists():
            shutil.rmtree(self.var)
        self.cell = PrivateCell(self.var, machines(seed), log, database_url, agent=True)
        self.conn: psycopg.Connection[Any] | None = None

    def run(self) -> dict[str, Any]:
        try:
            self.say("starting a private cell: the Mazak (wearing tool), wc2, the CMM simulator")
            self.cell.start(start_machines=False)
            self.conn = db.connect(self.cell.cfg, role="hi", log=self.log)
            self.conn.autocommit = True
            for m in ("cmm_wc", "mazak"):
                self._start(m)
            self._recipes(feedback=False)
            without = self._phase("without", self.parts)
            self._tool_change("mazak")
            self._recipes(feedback=True)
            with_ = self._phase("with", self.parts)
            self._recipes(feedback=False)
            assert self.cell.bus is not None
            shutdown(self.cell.bus, "wc:mazak", Conv.ME_SHUT)
            self._start("wc2")
            alarm = self._shift()
            return {
                "parts": self.parts,
                "seed": self.seed,
                "without": without,
                "with": with_,
                "spc_alarm_after_parts": alarm,
            }
        finally:
            if self.conn is not None:
                self.conn.close()
            self.cell.stop()

    # ----------------------------------------------------------------- the cell

    def _start(self, machine: str) -> None:
        assert self.cell.bus is not None
        startup(self.cell.bus, f"wc:{machine}", Conv.ME_START, timeout=60)

    def _recipes(self, feedback: bool) -> None:
        assert self.cell.bus is not None
        mill = (
            "# mill_pawn: a pawn, its features\nPROFILE pawn\n"
            + feature_lines()
            + (FEEDBACK + "\n" if feedback else "")
        )
        for recipe, body in (("mill_pawn", mill), ("alum_chess_set", "# CMM: measure a pawn\n" + feature_lines())):
            version = store_recipe(self.cell.bus, recipe, body).version
            approve_recipe(self.cell.bus, recipe, version)

    def _tool_change(self, machine: str) -> None:
        assert self.conn is not None
        self.conn.execute("INSERT INTO tool_changes (machine_id, confirmed_by) VALUES (%s, 'bench')", (machine,))

    def _rows(self, sql: str, *params: Any) -> list[tuple[Any, ...]]:
        assert self.conn is not None
        return self.conn.execute(sql, params).fetchall()

    def _make(self, n: int, stop: Callable[[], bool] | None = None) -> tuple[list[int], datetime]:
        """n parts, at most at_once lots at a time, the bench importing and exporting them; early if stop()."""
        assert self.cell.bus is not None
        since = self._rows("SELECT clock_timestamp()")[0][0]
        entities: list[int] = []
        decided: set[tuple[int, str]] = set()
        deadline = Deadline(PHASE_TIMEOUT)
        while not deadline.expired:
            states = dict(self._rows("SELECT entity_id, state FROM lot_status WHERE entity_id = ANY(%s)", entities))
            active = [e for e in entities if states.get(e) not in (LotState.EXPORTED, LotState.FAILED)]
            if stop is not None and stop() and not active:
                break
            if len(entities) == n and not active:
                break
            if len(entities) < n and len(active) < self.at_once and not (stop is not None and stop()):
                _, made = create_lot(self.cell.bus, "milled_pawn", 1, owner="bench")
                spawn_lot_script(self.cell.cfg, made[0])
                entities += made
            for e, s in states.items():
                action = {LotState.WAITING_IMPORT: "import", LotState.WAITING_EXPORT: "export"}.get(s)
                if action and (e, action) not in decided:
                    try:
                        decide(self.cell.bus, e, action, "bench")
                        decided.add((e, action))
                    except GwcError as err:
                        self.log.warning("%s of %d not taken: %s", action, e, err)
            time.sleep(0.02)
        else:
            raise ModuleError(f"the parts were not made within {PHASE_TIMEOUT:.0f}s")
        return entities, since

    def _phase(self, name: str, n: int) -> dict[str, Any]:
        self.say(f"{name} feedback: {n} parts")
        t0 = time.monotonic()
        entities, since = self._make(n)
        firsts = self._firsts("mazak", since)
        parts = {run for run, _f, _v, _ok in firsts}
        bad = {run for run, _f, _v, ok in firsts if not ok}
        remills = self._rows(
            "SELECT count(DISTINCT machine_run_id) FROM run_features WHERE machine_id = 'mazak' AND at >= %s "
            "AND workpiece IS NOT NULL AND measured IS NULL",
            since,
        )[0][0]
        results = self._rows("SELECT reason, state FROM lot_status WHERE entity_id = ANY(%s)", entities)
        cpk = {}
        for f, (nominal, tol) in FEATURES.items():
            _, k = spc.capability([v for _r, ff, v, _ok in firsts if ff == f], nominal - tol, nominal + tol)
            cpk[f] = None if k is None else round(k, 3)
        out = {
            "out_of_tolerance": len(bad),
            "out_of_tolerance_rate": round(len(bad) / max(1, len(parts)), 4),
            "remills": int(remills),
            "scrap": sum(1 for reason, _s in results if (reason or "").startswith("SCRAP")),
            "cpk": cpk,
            "failed": sum(1 for _r, s in results if s == LotState.FAILED),
            "measured": len(parts),
            "seconds": round(time.monotonic() - t0, 1),
        }
        self.say(f"  {out}")
        return out

    def _firsts(self, machine: str, since: datetime) -> list[tuple[int, str, float, bool]]:
        """(milling run, feature, measured, in tolerance) of each part's first cut on `machine` since."""
        rows = self._rows(
            "SELECT mk.machine_run_id, m.feature, m.measured, m.in_tol FROM run_features mk "
            "JOIN LATERAL (SELECT feature, measured, in_tol FROM run_features m WHERE m.workpiece = mk.machine_run_id "
            "  AND m.feature = mk.feature AND m.measured IS NOT NULL ORDER BY m.at LIMIT 1) m ON true "
            "WHERE mk.machine_id = %s AND mk.at >= %s AND mk.workpiece IS NULL AND mk.measured IS NULL",
            machine,
            since,
        )
        firsts: dict[int, list[tuple[str, float, bool]]] = {}
        for run, f, v, ok in rows:
            firsts.setdefault(int(run), []).append((str(f), float(v), bool(ok)))
        return [(run, f, v, all(o for _f, _v, o in feats)) for run, feats in firsts.items() for f, v, _ok in feats]

    def _shift(self) -> int | None:
        self.say(f"step shift: wc2 makes {SHIFT_AFTER} parts, then its DIAMETER moves 2 sigma")

        def alarmed() -> bool:
            return bool(self._rows("SELECT 1 FROM alarms WHERE alarm_id = 'SPC_RULE' AND machine_id = 'wc2'"))

        # One part at a time after the shift's start, so that the count is of parts, not of lots in flight.
        self.at_once = 1
        self._make(SHIFT_AFTER + SHIFT_PARTS, stop=alarmed)
        texts = [
            t for (t,) in self._rows("SELECT alarm_text FROM alarms WHERE alarm_id = 'SPC_RULE' AND machine_id = 'wc2'")
        ]
        found = [int(m.group(1)) for t in texts if (m := re.search(r"at part (\d+)", t))]
        return (min(found) - SHIFT_AFTER) if found else None


def _line(name: str, r: dict[str, Any]) -> str:
    return (
        f"{name:8s} {r['out_of_tolerance']:4d} out of tolerance ({100 * r['out_of_tolerance_rate']:.1f}%), "
        f"{r['remills']} re-millings, {r['scrap']} scrap, Cpk "
        + ", ".join(f"{f} {'-' if v is None else f'{v:.2f}'}" for f, v in r["cpk"].items())
        + f"  ({r['seconds']:.0f}s)"
    )


@click.command("quality")
@click.option("--parts", default=200, show_default=True, help="Parts made with feedback off, then as many with it on.")
@click.option("--seed", default=1, show_default=True, help="Seeds the mills' processes and the CMM's gauge.")
@click.option("--at-once", default=3, show_default=True, help="Lots at work at a time.")
@click.option("--where", type=click.Path(path_type=Path), default=None, help="The private cell's var/.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def command(parts: int, seed: int, at_once: int, where: Path | None, as_json: bool) -> None:
    """The same simulated tool wear, feedback off then on, side by side: parts out of tolerance,
    re-millings, scrap, Cpk per feature; and the parts from an injected 2-sigma step shift to its SPC
    alarm. Uses $GWC_DATABASE_URL if set, else an embedded cluster of its own."""
    if parts < 1 or at_once < 1:
        raise click.BadParameter("--parts and --at-once must be at least 1")
    cfg, log = bench_context()
    bench = QualityBench(
        where or cfg.var / "bench-quality",
        parts,
        seed,
        at_once,
        os.environ.get("GWC_DATABASE_URL"),
        log,
        (lambda s: None) if as_json else click.echo,
    )
    result = bench.run()
    if as_json:
        import json

        click.echo(json.dumps(result, indent=1))
        return
    click.echo(f"{result['parts']} parts each way, seed {result['seed']}:")
    click.echo(_line("without", result["without"]))
    click.echo(_line("with", result["with"]))
    click.echo(f"step shift of 2 sigma alarmed by SPC after {result['spc_alarm_after_parts']} part(s)")
