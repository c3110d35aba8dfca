"""The simulated mill's process: what a part's features come out as, and the part itself.

Each feature is made as nominal + the run's offset + the machine's bias + tool wear (growing with the
parts cut since the last tool change) + a shift injected after a number of parts + noise, all per
machine in the [[machine]] entry of etc/cell.toml, seeded (docs/quality.md):

    process = { seed = 7, bias = { DIAMETER = 0.01 }, wear = { DIAMETER = 0.0005 },
                sigma = { DIAMETER = 0.006, HEIGHT = 0.012 }, shift = { after = 30, DIAMETER = 0.012 } }

A re-milling (the run sheet names the workpiece) can only take material off: each feature is the
smaller of the part's and the cut's. The part made is written where the CMM simulator finds it
(var/sim/parts/run-<machine_run_id>.json): the part travels from the mill to the CMM.
The tool's state (parts cut, tool changes seen) is kept in the machine's memory directory, so an ME
restart loses nothing; a TOOL count in the run sheet larger than the one seen is a tool change.
"""

from __future__ import annotations

import json
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gwc.errors import ConfigError
from gwc.files import rewrite
from gwc.quality.recipe import Feature
from gwc.quality.sheet import RunSheet

TOOL_FILE = "tool.json"


def parts_dir(var: Path) -> Path:
    """Where simulated parts are kept between the machines that work on them."""
    return var / "sim" / "parts"


def part_file(var: Path, machine_run_id: int) -> Path:
    return parts_dir(var) / f"run-{machine_run_id}.json"


def read_part(var: Path, machine_run_id: int) -> dict[str, float] | None:
    """The features of the part run `machine_run_id` made, or None if no simulated machine made it."""
    try:
        data = json.loads(part_file(var, machine_run_id).read_text())
    except (OSError, ValueError):
        return None
    return {str(k): float(v) for k, v in data.items() if isinstance(v, int | float)} if isinstance(data, dict) else None


def _table(where: str, value: Any) -> dict[str, float]:
    if value is None:
        return {}
    if not isinstance(value, dict) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value.values()
    ):
        raise ConfigError(f"{where} must be a table of feature = number")
    return {str(k): float(v) for k, v in value.items()}


@dataclass
class MillProcess:
    seed: int
    bias: dict[str, float] = field(default_factory=dict)
    wear: dict[str, float] = field(default_factory=dict)
    sigma: dict[str, float] = field(default_factory=dict)
    shift: dict[str, float] = field(default_factory=dict)
    shift_after: int = 0

    @classmethod
    def from_options(cls, machine_id: str, value: Any) -> MillProcess | None:
        """The process of a machine's `process` table, or None where nothing is configured (today's dummy)."""
        if value is None:
            return None
        where = f"machine {machine_id}: process"
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a table")
        unknown = set(value) - {"seed", "bias", "wear", "sigma", "shift"}
        if unknown:
            raise ConfigError(f"{where}: unknown option(s) {', '.join(sorted(unknown))}")
        seed = value.get("seed", 1)
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise ConfigError(f"{where}.seed must be an integer")
        shift = dict(value.get("shift") or {})
        after = shift.pop("after", 0)
        if not isinstance(after, int) or isinstance(after, bool) or after < 0:
            raise ConfigError(f"{where}.shift.after must be a count of parts")
        sigma = _table(f"{where}.sigma", value.get("sigma"))
        if any(s < 0 for s in sigma.values()):
            raise ConfigError(f"{where}.sigma must not be negative")
        return cls(
            seed,
            _table(f"{where}.bias", value.get("bias")),
            _table(f"{where}.wear", value.get("wear")),
            sigma,
            _table(f"{where}.shift", shift),
            after,
        )

    def cut(
        self,
        features: list[Feature],
        sheet: RunSheet | None,
        made_before: int,
        run_no: int,
        old: dict[str, float] | None,
    ) -> dict[str, float]:
        """The features of the part cut now, the `made_before`-th part since the tool change."""
        rng = random.Random(f"{self.seed}:{run_no}")
        offsets = sheet.offsets if sheet is not None else {}
        part = {}
        for f in features:
            value = (
                f.nominal
                + offsets.get(f.name, 0.0)
                + self.bias.get(f.name, 0.0)
                + self.wear.get(f.name, 0.0) * made_before
                + (self.shift.get(f.name, 0.0) if self.shift and made_before >= self.shift_after else 0.0)
                + rng.gauss(0.0, self.sigma.get(f.name, 0.0))
            )
            if old is not None and f.name in old:
                value = min(value, old[f.name])
            part[f.name] = round(value, 6)
        return part


class Tool:
    """The tool's wear state of one machine, kept in its memory directory across ME restarts."""

    def __init__(self, memory: Path) -> None:
        self.path = memory / TOOL_FILE
        self.changes, self.parts = 0, 0
        try:
            data = json.loads(self.path.read_text())
            self.changes, self.parts = int(data["changes"]), int(data["parts"])
        except (OSError, ValueError, KeyError, TypeError):
            pass

    def seen(self, changes: int) -> bool:
        """A run sheet's TOOL count: larger than the last seen means the tool was changed. True if it was."""
        if changes > self.changes:
            self.changes, self.parts = changes, 0
            self._save()
            return True
        return False

    def cut_one(self) -> int:
        """One part cut: the number cut before it since the tool change."""
        before = self.parts
        self.parts += 1
        self._save()
        return before

    def _save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        rewrite(self.path, json.dumps({"changes": self.changes, "parts": self.parts}).encode())


def write_part(var: Path, machine_run_id: int, part: dict[str, float]) -> Path:
    path = part_file(var, machine_run_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(part))
    tmp.replace(path)
    return path


def measure(features: list[Feature], part: dict[str, float] | None, seed: str, gauge_sigma: float) -> dict[str, float]:
    """A gauge's reading of each feature of `part` (a nominal part if None): the value plus the gauge's noise."""
    rng = random.Random(seed)
    return {f.name: round((part or {}).get(f.name, f.nominal) + rng.gauss(0.0, gauge_sigma), 6) for f in features}
