"""A run's own lines after its recipe: the run sheet (the offsets the feedback gives this run, and the part).

The approved recipe is never changed: the WC gives the machine a copy of it with these lines after it,
as a CNC's operator keys tool offsets in beside the program (gwc/wc/steps.py, `sheet` of SETUP_RUN):

    # run sheet (gwc): this run's own lines; the recipe above is the approved version
    RUN 123                       the machine_run_id
    WORKPIECE 120                 the run that made the part this run works on (measures, re-mills)
    TOOL 1795865532123            the machine's last tool change or maintenance, ms since the epoch
    OFFSET DIAMETER -0.0123       added to the feature's nominal by a machine that makes it

The ME puts WORKPIECE and each OFFSET.<feature> in its results, so they are stored with the run.
"""

from __future__ import annotations

import math
import re
from collections.abc import Awaitable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MARK = "# run sheet (gwc): this run's own lines; the recipe above is the approved version"
NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")
MAX_OFFSET = 1000.0  # an offset larger than this is a mistake, not a correction


@dataclass(frozen=True)
class RunSheet:
    machine_run_id: int = 0
    workpiece: int | None = None
    tool: int = 0
    offsets: dict[str, float] = field(default_factory=dict)

    def text(self) -> str:
        lines = [MARK, f"RUN {self.machine_run_id}"]
        if self.workpiece is not None:
            lines.append(f"WORKPIECE {self.workpiece}")
        lines.append(f"TOOL {self.tool}")
        lines += [f"OFFSET {k} {v:.6f}" for k, v in sorted(self.offsets.items())]
        return "\n".join(lines) + "\n"

    def message(self) -> dict[str, Any]:
        """The SETUP_RUN field `sheet` (the WC adds the run)."""
        return {"workpiece": self.workpiece, "tool": self.tool, "offsets": dict(self.offsets)}

    def results(self) -> dict[str, str]:
        """What the ME reports of it with the run's results."""
        out = {f"OFFSET.{k}": f"{v:.6f}" for k, v in sorted(self.offsets.items())}
        if self.workpiece is not None:
            out["WORKPIECE"] = str(self.workpiece)
        return out


def from_message(value: Any, machine_run_id: int) -> RunSheet:
    """SETUP_RUN's `sheet` checked: ValueError saying what is wrong (the WC refuses the setup with it)."""
    if not isinstance(value, dict):
        raise ValueError("sheet must be a table")
    unknown = set(value) - {"workpiece", "tool", "offsets"}
    if unknown:
        raise ValueError(f"sheet: unknown field(s) {', '.join(sorted(unknown))}")
    piece = value.get("workpiece")
    if piece is not None and (not isinstance(piece, int) or isinstance(piece, bool) or piece <= 0):
        raise ValueError(f"sheet: workpiece must be a run id, got {piece!r}")
    tool = value.get("tool", 0)
    if not isinstance(tool, int) or isinstance(tool, bool) or tool < 0:
        raise ValueError(f"sheet: tool must be a count, got {tool!r}")
    offsets = value.get("offsets") or {}
    if not isinstance(offsets, dict):
        raise ValueError("sheet: offsets must be a table of feature -> number")
    checked = {}
    for k, v in offsets.items():
        if not isinstance(k, str) or not NAME.match(k):
            raise ValueError(f"sheet: offset name {k!r} is not a feature name")
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or abs(v) > MAX_OFFSET:
            raise ValueError(f"sheet: offset {k} = {v!r} is not a number within +/-{MAX_OFFSET:g}")
        checked[k] = float(v)
    return RunSheet(machine_run_id, piece, tool, checked)


def read_sheet(text: str) -> RunSheet | None:
    """The run sheet at the end of a recipe copy, or None (a recipe given as approved, without one)."""
    at = text.rfind(MARK)
    if at < 0:
        return None
    run, piece, tool, offsets = 0, None, 0, {}
    for line in text[at + len(MARK) :].splitlines():
        words = line.split()
        try:
            if words[:1] == ["RUN"] and len(words) == 2:
                run = int(words[1])
            elif words[:1] == ["WORKPIECE"] and len(words) == 2:
                piece = int(words[1])
            elif words[:1] == ["TOOL"] and len(words) == 2:
                tool = int(words[1])
            elif words[:1] == ["OFFSET"] and len(words) == 3:
                offsets[words[1]] = float(words[2])
        except ValueError:
            continue
    return RunSheet(run, piece, tool, offsets)


def write_sheet(recipe: Path, sheet: RunSheet) -> Path:
    """The machine's copy of the approved recipe with the run sheet after it, beside it (one per recipe
    file: a WC sets up one run at a time), written whole then renamed."""
    path = recipe.with_name(f"{recipe.name}.run")
    content = recipe.read_bytes()
    if content and not content.endswith(b"\n"):
        content += b"\n"
    tmp = path.with_name(f"{path.name}.tmp")
    tmp.write_bytes(content + sheet.text().encode())
    tmp.replace(path)
    return path


async def with_sheet(
    fetch: Awaitable[tuple[Path | None, str]], value: Any, machine_run_id: int
) -> tuple[Path | None, str]:
    """The WC's hook: the approved recipe `fetch` gives, with the run sheet of SETUP_RUN after it (a copy):
    (None, why) for a sheet that is not one, as for a recipe refused."""
    path, why = await fetch
    if path is None:
        return path, why
    try:
        return write_sheet(path, from_message(value, machine_run_id)), ""
    except ValueError as e:
        return None, str(e)
    except OSError as e:
        return None, f"run sheet for run {machine_run_id} not written: {e}"


def sheet_of(path: Path) -> RunSheet | None:
    """The run sheet of a recipe file the ME was given (None: none, or the file unreadable)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if MARK.encode() not in data:
        return None
    return read_sheet(data.decode("utf-8", "replace"))
