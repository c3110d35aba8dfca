"""The dummy machine: the thesis's MEN (Listing 7), N of them, each a configurable stand-in.

Section 7.4 built it to show that the cell runs any number of machines through one interface. It
acknowledges every request, takes `run_time` seconds per run and writes a results file of
param/value pairs. Unlike Listing 7 it can be told, in its [[machine]] entry of etc/cell.toml, to
behave like a real machine that needs an operator or goes wrong:

    run_time = 0.2              # seconds a run takes (default 1.0)
    setup_time = 0.0            # seconds SETUP_RUN takes before it is acknowledged
    homing_alarm = true         # raise HOME_CMM at ME_START, as the CMM does (or name another alarm id)
    fail_runs = [2]             # these runs (RUN_NO, counted across ME restarts) end Run_Fail;
                                # true: every run fails
    fail_start = true           # refuse ME_START (homing fails): the WC answers Start_Fail
    results = { DIAMETER = "25.02" }   # extra param/value pairs in every results file
    process = { seed = 7, wear = { DIAMETER = 0.0005 }, sigma = { DIAMETER = 0.006 } }
                                # a mill with a process: each run cuts a part of the recipe's FEATUREs
                                # (gwc/quality/process.py, docs/quality.md)
    gauge_sigma = 0.0005        # without a process, given a recipe with FEATUREs and a part (WORKPIECE):
                                # it measures the part, as the CMM simulator does
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError
from gwc.ipc.codes import AckCode
from gwc.me.machine import MachineSide, Refusal, RunOutcome
from gwc.quality.process import MillProcess, Tool, measure, read_part, write_part
from gwc.quality.recipe import Feature, features_of


class DummyMachine(MachineSide):
    kind = "dummy"
    # Nothing to watch between runs, and a request or a signal ends the wait at once: each turn of its
    # loop is only a wake-up of a resting machine (docs/performance.md, A resting cell). Its WC pings
    # it every 5 s anyway; the bound is for a SIGTERM that comes between the loop's look at `stop` and
    # its wait.
    idle_poll = 10.0

    def __init__(self, cfg: Config, spec: MachineSpec, log: logging.Logger) -> None:
        super().__init__(cfg, spec, log)
        self.run_time = self.options.get("run_time", float, 1.0)
        self.setup_time = self.options.get("setup_time", float, 0.0)
        self.fail_start = self.options.get("fail_start", bool, False)
        fail = self.options.get("fail_runs", (bool, list), [])
        if isinstance(fail, list) and not all(isinstance(n, int) and not isinstance(n, bool) for n in fail):
            raise ConfigError(f"machine {spec.id}: fail_runs must be a list of run numbers or true")
        self.fail_runs: bool | set[int] = fail if isinstance(fail, bool) else set(fail)
        self.extra = {str(k): str(v) for k, v in self.options.get("results", dict, {}).items()}
        self._ends_at = 0.0
        self.process = MillProcess.from_options(spec.id, spec.options.get("process"))
        self.tool = Tool(self.memory) if self.process is not None else None
        self.features: list[Feature] = []
        self.gauge_sigma = self.options.get("gauge_sigma", float, 0.0005)  # measuring: the gauge's noise

    def home(self) -> None:
        if self.fail_start:
            raise Refusal(AckCode.START_FAIL, "the machine failed to home (fail_start)")

    def load(self, recipe_id: str, path: Path) -> None:
        self.features = features_of(path.read_text(errors="replace"))
        if self.setup_time:
            time.sleep(self.setup_time)

    def begin(self) -> None:
        self._ends_at = time.monotonic() + self.run_time

    def progress(self) -> RunOutcome | None:
        if time.monotonic() < self._ends_at:
            return None
        fails = self.fail_runs is True or (isinstance(self.fail_runs, set) and self.run_no in self.fail_runs)
        if fails:
            return RunOutcome(AckCode.RUN_FAIL, {"RESULT": "FAIL", **self.extra}, note="configured to fail")
        return RunOutcome(
            AckCode.ACK_OK, {"RESULT": "PASS", "PARTS": "1", **self.extra, **self._cut(), **self._measure()}
        )

    def _measure(self) -> dict[str, str]:
        """A dummy without a process given a recipe with FEATUREs and a part (its sheet's WORKPIECE) is a
        measuring machine: it reports each feature's value (gauge noise `gauge_sigma`) and the verdict."""
        sheet = self.sheet
        if self.process is not None or not self.features or sheet is None or not sheet.workpiece:
            return {}
        values = measure(
            self.features, read_part(self.cfg.var, sheet.workpiece), f"{self.spec.id}:{self.run_no}", self.gauge_sigma
        )
        passed = all(f.passes(values[f.name]) for f in self.features)
        return {**{k: f"{v:.6f}" for k, v in values.items()}, "RESULT": "PASS" if passed else "FAIL"}

    def _cut(self) -> dict[str, str]:
        """A mill with a process cuts the part of its recipe's features and leaves it for the CMM."""
        if self.process is None or self.tool is None or not self.features:
            return {}
        sheet = self.sheet
        if sheet is not None and self.tool.seen(sheet.tool):
            self.log.info("tool change %d seen: wear starts again", sheet.tool)
        old = read_part(self.cfg.var, sheet.workpiece) if sheet is not None and sheet.workpiece else None
        before = self.tool.cut_one()
        part = self.process.cut(self.features, sheet, before, self.run_no, old)
        if sheet is not None and sheet.machine_run_id:
            write_part(self.cfg.var, sheet.machine_run_id, part)
        self.log.info("cut part %d since the tool change: %s", before + 1, part)
        return {"TOOL_PARTS": str(before + 1)}

    def abort(self, why: str) -> None:
        self.log.warning("run %d abandoned: %s", self.run_no, why)
