"""Quality for a lot script: the feedback's offsets in each milling's run sheet, the verdict from the
measured features, SPC alarms, TOOL_CHANGE (docs/quality.md, docs/lot-scripts.md).

    q = Quality(entity)
    mill = entity.operate("mill_chess", sheet=q.mill_sheet())
    measure = entity.operate("alum_chess", sheet=q.measure_sheet(mill))
    ok, why = q.verdict(measure)
    q.check_spc(mill)

Nothing here is kept in the process: the offsets are computed from the runs stored in the database
(gwc/quality/feedback.py), so a lot script killed and restarted carries on from the same state.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Protocol

from gwc.config import Config
from gwc.errors import GwcError
from gwc.lot.errors import MachineLost
from gwc.lot.model import UP, Operation
from gwc.lot.runs import Sheets
from gwc.quality import spc, store
from gwc.quality.feedback import feed_forward, next_offset
from gwc.quality.sheet import RunSheet
from gwc.quality.spc import settings as spc_settings
from gwc.quality.store import Reader
from gwc.retry import Deadline

WORN_WAIT = 15.0  # s: how long a worn tool's machine is given to go down after TOOL_CHANGE


class Entity(Protocol):
    """What Quality needs of an OperationEntity."""

    entity_id: int
    cfg: Config
    log: logging.Logger

    def read(self, sql: str, params: Any = ()) -> list[tuple[Any, ...]]: ...

    def raise_alarm(self, alarm_id: str, machine_id: str, text: str) -> int | None: ...


class ToolWorn(MachineLost):
    """The machine's tool is worn out: TOOL_CHANGE raised, the machine going down until the operator
    confirms the change (`gwc tool change`); the operation is asked again (another alternative, or
    this machine once it is back)."""


class Quality:
    def __init__(self, entity: Entity) -> None:
        self.entity = entity
        self.read: Reader = entity.read
        self.rules, self.baseline, self.window = spc_settings(entity.cfg)
        self.yield_window = int(entity.cfg.raw.get("quality", {}).get("yield_window", 20))
        self.offsets: dict[int, dict[str, float]] = {}  # offsets given, by machine_run_id (for the log)

    # ----------------------------------------------------------------- run sheets

    def mill_sheet(self, remill: Operation | None = None, measured: Operation | None = None) -> Sheets:
        """The run sheet of a milling: the feedback's offsets for the machine MSCHED gave (recipe with
        FEEDBACK), zero offsets (FEATUREs without FEEDBACK), nothing (a recipe without FEATUREs). For a
        re-milling of `remill`'s part: the correction its own measurement (`measured`) asks for (feed forward)."""

        def make(machine_id: str, recipe_id: str) -> dict[str, Any] | None:
            feats = store.features(self.read, recipe_id)
            if not feats:
                return None
            tool = store.tool_changes(self.read, machine_id)
            offsets = {f.name: 0.0 for f in feats}
            piece = remill.machine_run_id if remill is not None else None
            if remill is not None:
                if store.feedback(self.read, recipe_id) is not None and measured is not None:
                    offsets.update(self.correction(remill, measured))
            else:
                fb = store.feedback(self.read, recipe_id)
                if fb is not None:
                    worn = []
                    for f in feats:
                        advice = next_offset(store.history(self.read, machine_id, recipe_id, f.name), fb)
                        offsets[f.name] = advice.offset
                        if advice.worn:
                            worn.append(f"{f.name} needs {advice.needed:+.4f} (limit {fb.total_limit:g})")
                    if worn:
                        self._worn(machine_id, recipe_id, worn)
            return RunSheet(0, piece, tool, offsets).message()

        return make

    def measure_sheet(self, made: Operation) -> Sheets | None:
        """The run sheet of a measurement of the part `made` made: its WORKPIECE (None if `made` had no features)."""
        if not self.features_of(made):
            return None
        piece = made.machine_run_id
        return lambda machine_id, recipe_id: RunSheet(0, piece, 0, {}).message()

    def correction(self, made: Operation, measured: Operation) -> dict[str, float]:
        """Feed forward: per feature, the offset `made` used less what `measured` found it off by."""
        used = {r["feature"]: r["offset"] or 0.0 for r in self.features_of(made)}
        return {
            r["feature"]: feed_forward(used.get(r["feature"], 0.0), r["measured"] - r["nominal"])
            for r in self.features_of(measured)
            if r["measured"] is not None
        }

    # ----------------------------------------------------------------- which machine is better

    def preferred(self, op_type: str) -> list[list[str]] | None:
        """The machines qualified for op_type that are up, one alternative each, the best yield first (6.1:
        "the results from machine M1 are better than those from machine M2"): MSCHED binds, of the
        alternatives free at once, the first asked for, and never leaves the lot waiting for a busy
        one while another is free. None (the entity's own choice) when no machine has a history yet.
        Ties: the machine with fewer parts measured first (so each is tried), then by name."""
        machines = [
            str(m)
            for (m,) in self.read(
                "SELECT DISTINCT r.machine_id FROM op_machine_recipe r JOIN machine_status s USING (machine_id) "
                "WHERE r.op_type = %s AND s.status = ANY(%s) ORDER BY 1",
                (op_type, list(UP)),
            )
        ]
        if len(machines) < 2:
            return None
        ys = store.yields(self.read, op_type, machines, self.yield_window)
        if not any(y.parts for y in ys.values()):
            return None
        order = sorted(machines, key=lambda m: (-ys[m].rate, ys[m].parts, m))
        self.entity.log.info(
            "%s: machines by yield %s",
            op_type,
            ", ".join(f"{m} {ys[m].good}/{ys[m].parts}" for m in order),
        )
        return [[m] for m in order]

    # ----------------------------------------------------------------- verdict, SPC

    def features_of(self, op: Operation) -> list[dict[str, Any]]:
        return store.run_features(self.read, op.machine_run_id)

    def verdict(self, measured: Operation) -> tuple[bool, str] | None:
        """From the measured features and their tolerances (thesis 3.2.3), or None if none were measured."""
        rows = [r for r in self.features_of(measured) if r["measured"] is not None]
        if not rows:
            return None
        out = [r for r in rows if not r["in_tol"]]
        said = ", ".join(f"{r['feature']} {r['measured']:.4f} ({r['nominal']:g} +/- {r['tol']:g})" for r in rows)
        return (not out, ("FAIL: " if out else "within tolerance: ") + said)

    def check_spc(self, made: Operation) -> list[str]:
        """The charts of the machine and recipe that made the part: a rule broken at the newest point raises
        SPC_RULE naming the machine, feature and rule (once while one is pending for that feature)."""
        run = made.runs[0] if made.runs else None
        if run is None:
            return []
        points = store.points(self.read, machine_id=run.machine_id, recipe_id=run.recipe_id, limit=self.window)
        raised = []
        for feature in sorted({p.feature for p in points}):
            series = [p for p in points if p.feature == feature]
            values = [p.value for p in series]
            c = spc.chart(
                feature,
                values,
                series[-1].nominal - series[-1].tol,
                series[-1].nominal + series[-1].tol,
                self.rules,
                self.baseline,
            )
            latest = [v for v in c.violations if v.index == len(values) - 1]
            if not latest or store.pending_alarm(self.read, run.machine_id, "SPC_RULE", f"% {feature} %"):
                continue
            text = (
                f"{run.machine_id} {feature} (recipe {run.recipe_id}): {latest[0].text} at part {len(values)}, "
                f"run {series[-1].machine_run_id}"
            )
            try:
                self.entity.raise_alarm("SPC_RULE", run.machine_id, text)
            except GwcError as e:  # the part is made and measured: an alarm refused does not fail the lot
                self.entity.log.error("SPC_RULE not raised (%s): %s", e, text)
                continue
            raised.append(text)
        return raised

    # ----------------------------------------------------------------- TOOL_CHANGE

    def _worn(self, machine_id: str, recipe_id: str, why: list[str]) -> None:
        text = f"{machine_id} tool worn out (recipe {recipe_id}): " + "; ".join(why)
        if not store.pending_alarm(self.read, machine_id, "TOOL_CHANGE"):
            self.entity.raise_alarm("TOOL_CHANGE", machine_id, text)
        deadline = Deadline(WORN_WAIT)  # the Cell Alarm Server shuts it down: ask again once it has
        while not deadline.expired:
            rows = self.read("SELECT status FROM machine_status WHERE machine_id = %s", (machine_id,))
            if rows and rows[0][0] == "Shutdown":
                break
            time.sleep(0.2)
        raise ToolWorn(text)
